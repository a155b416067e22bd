// Sources of a stored project, read back from their blobs (flows.h).
#include <chrono>
#include <cstring>
#include <string>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_split.h"
#include "lattice/ingest/backproject.h"
#include "lattice/flows/flows.h"
#include "lattice/ingest/artefacts.h"
#include "lattice/ingest/voxelise.h"

namespace vasl::flows {
namespace {

/// What a source cost to make since `t0`: its worth in the revisit cache (SourceImageCache).
double SecondsSince(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

}  // namespace

ingest::LidarSource LidarOf(const store::SourceInfo& s, int32_t batch) {
  ingest::LidarSource out;
  out.id = s.id;
  out.batch = batch;
  out.pose = s.pose;
  out.divergence_rad = s.divergence_rad;
  return out;
}

ingest::CameraSource CameraOf(const store::SourceInfo& s, int32_t batch) {
  ingest::CameraSource cam;
  cam.id = s.id;
  cam.batch = batch;
  cam.pose = s.pose;
  cam.modality = s.modality;
  cam.angular_resolution_rad = s.divergence_rad;
  if (absl::StatusOr<std::optional<geometry::PinholeIntrinsics>> k = ProjectionOfCameraText(s.camera);
      k.ok()) {
    cam.pinhole = *k;
  }
  return cam;
}

absl::StatusOr<ingest::LidarSource> LoadLidar(const store::ProjectStore& store,
                                              const store::SourceInfo& s, int32_t batch) {
  absl::StatusOr<std::string> bytes = store.ReadBlob(s.blob_sha256);
  if (!bytes.ok()) return bytes.status();
  // Points (16 bytes each), then with a range grid each point's cell (4) and the grid's shape
  // (8): PackPoints. The catalog's point count tells the two apart.
  const size_t counted = size_t(std::max<int64_t>(0, s.point_count));
  const bool grid = counted > 0 && bytes->size() == counted * 20 + 8;
  if (!grid && bytes->size() % 16 != 0) {
    return absl::DataLossError(
        absl::StrCat("points blob ", s.blob_sha256, " is not a whole number of points"));
  }
  ingest::LidarSource out = LidarOf(s, batch);
  const size_t n = grid ? counted : bytes->size() / 16;
  if (grid) {
    uint32_t shape[2];
    std::memcpy(shape, bytes->data() + n * 20, 8);
    out.grid_rows = int32_t(shape[0]);
    out.grid_columns = int32_t(shape[1]);
    out.grid_cell.resize(n);
    std::memcpy(out.grid_cell.data(), bytes->data() + n * 16, n * 4);
    const uint64_t cells = uint64_t(shape[0]) * shape[1];
    for (uint32_t c : out.grid_cell) {
      if (c >= cells) {
        return absl::DataLossError(absl::StrCat("points blob ", s.blob_sha256, ": a grid cell ",
                                                c, " beyond its ", shape[0], "x", shape[1],
                                                " grid"));
      }
    }
  }
  out.xyz_sensor_m.resize(3 * n);
  out.intensity.resize(n);
  for (size_t i = 0; i < n; ++i) {
    float rec[4];
    std::memcpy(rec, bytes->data() + i * 16, 16);
    std::copy(rec, rec + 3, &out.xyz_sensor_m[3 * i]);
    out.intensity[i] = rec[3];
  }
  return out;
}

std::string PointColourCameraText(const std::string& lidar_blob_sha256) {
  return "points " + lidar_blob_sha256;
}

bool IsPointColour(const store::SourceInfo& source) {
  return source.modality != records::Modality::kLidar && source.camera.rfind("points ", 0) == 0;
}

absl::StatusOr<ingest::LidarSource> LoadPointColour(const store::ProjectStore& store,
                                                    const store::SourceInfo& s, int32_t batch) {
  store::SourceInfo points = s;
  points.blob_sha256 = s.camera.substr(std::strlen("points "));
  absl::StatusOr<ingest::LidarSource> out = LoadLidar(store, points, batch);
  if (!out.ok()) return out.status();
  absl::StatusOr<std::string> bytes = store.ReadBlob(s.blob_sha256);
  if (!bytes.ok()) return bytes.status();
  if (bytes->size() != out->point_count() * 12) {
    return absl::DataLossError(absl::StrCat("colour blob ", s.blob_sha256, " holds ",
                                            bytes->size() / 12, " colours for ",
                                            out->point_count(), " points"));
  }
  out->rgb.resize(3 * out->point_count());
  std::memcpy(out->rgb.data(), bytes->data(), bytes->size());
  out->intensity.clear();
  out->colour_id = s.id;
  return out;
}

std::string DerivedCameraText(bool pinhole, const geometry::PinholeIntrinsics& k,
                              int64_t render_id) {
  std::string s =
      !pinhole ? std::string("equirect")
      : k.lens == geometry::Lens::kFisheye
          ? absl::StrFormat("fisheye %.17g %.17g %.17g %.17g %.17g %.17g %.17g %.17g%s",
                            k.fx_px, k.fy_px, k.cx_px, k.cy_px, k.k1, k.k2, k.k3, k.k4,
                            k.field_of_view_rad > 0.0
                                ? absl::StrFormat(" field %.17g", k.field_of_view_rad)
                                : std::string())
          : absl::StrFormat("pinhole %.17g %.17g %.17g %.17g %.17g %.17g %.17g %.17g %.17g",
                            k.fx_px, k.fy_px, k.cx_px, k.cy_px, k.k1, k.k2, k.k3, k.p1, k.p2);
  if (render_id > 0) absl::StrAppend(&s, " render ", render_id);
  return s;
}

absl::StatusOr<std::optional<geometry::PinholeIntrinsics>> ProjectionOfCameraText(
    const std::string& camera_text) {
  std::vector<std::string> f = absl::StrSplit(camera_text, ' ', absl::SkipEmpty());
  if (f.empty() || f[0] == "equirect") return std::nullopt;
  const bool fisheye = f[0] == "fisheye";
  const size_t numbers = fisheye ? 8 : 9;  // fx fy cx cy k1 k2 k3, then k4 or p1 p2
  if ((f[0] != "pinhole" && !fisheye) || f.size() < numbers + 1) {
    return absl::DataLossError(absl::StrCat("bad camera text '", camera_text, "'"));
  }
  geometry::PinholeIntrinsics k;
  if (fisheye) k.lens = geometry::Lens::kFisheye;
  double* v[] = {&k.fx_px, &k.fy_px, &k.cx_px, &k.cy_px, &k.k1, &k.k2, &k.k3,
                 fisheye ? &k.k4 : &k.p1, &k.p2};
  for (size_t i = 0; i < numbers; ++i) {
    if (!absl::SimpleAtod(f[i + 1], v[i])) {
      return absl::DataLossError(absl::StrCat("bad camera text '", camera_text, "'"));
    }
  }
  if (fisheye && f.size() >= 11 && f[9] == "field" &&
      !absl::SimpleAtod(f[10], &k.field_of_view_rad)) {
    return absl::DataLossError(absl::StrCat("bad camera text '", camera_text, "'"));
  }
  return k;
}

std::string SphereCameraText(const ingest::SphereWindow& window) {
  return absl::StrFormat("equirect window %d %d", window.left_px, window.top_px);
}

std::string CylinderCameraText(const ingest::CylinderImage& c) {
  return absl::StrFormat("equirect cylinder %.17g %.17g %.17g %.17g", c.pixel_width_rad,
                         c.pixel_height_m, c.radius_m, c.principal_y_px);
}

absl::StatusOr<std::optional<ingest::SphereWindow>> SphereOfCameraText(
    const store::SourceInfo& src) {
  std::vector<std::string> f = absl::StrSplit(src.camera, ' ', absl::SkipEmpty());
  if (f.size() < 2 || f[0] != "equirect" || f[1] != "window") return std::nullopt;
  ingest::SphereWindow w{src.width_px, src.height_px, 0, 0};
  if (f.size() != 4 || !absl::SimpleAtoi(f[2], &w.left_px) || !absl::SimpleAtoi(f[3], &w.top_px)) {
    return absl::DataLossError(absl::StrCat("bad camera text '", src.camera, "'"));
  }
  return w;
}

absl::StatusOr<std::optional<ingest::CylinderImage>> CylinderOfCameraText(
    const std::string& camera_text) {
  std::vector<std::string> f = absl::StrSplit(camera_text, ' ', absl::SkipEmpty());
  if (f.size() < 2 || f[0] != "equirect" || f[1] != "cylinder") return std::nullopt;
  ingest::CylinderImage c;
  if (f.size() != 6 || !absl::SimpleAtod(f[2], &c.pixel_width_rad) ||
      !absl::SimpleAtod(f[3], &c.pixel_height_m) || !absl::SimpleAtod(f[4], &c.radius_m) ||
      !absl::SimpleAtod(f[5], &c.principal_y_px)) {
    return absl::DataLossError(absl::StrCat("bad camera text '", camera_text, "'"));
  }
  return c;
}

bool PartOfTheSphere(const store::SourceInfo& src) {
  return absl::StartsWith(src.camera, "equirect window") ||
         absl::StartsWith(src.camera, "equirect cylinder");
}

absl::StatusOr<ingest::DerivedSource> LoadDerived(const store::ProjectStore& store,
                                                  const store::SourceInfo& src, int32_t batch,
                                                  int64_t max_pixels) {
  ingest::DerivedSource out;
  out.id = src.id;
  out.batch = batch;
  out.pose = src.pose;
  absl::StatusOr<std::optional<geometry::PinholeIntrinsics>> k = ProjectionOfCameraText(src.camera);
  if (!k.ok() || src.camera.empty()) {
    return absl::DataLossError(absl::StrCat("source ", src.id, ": bad camera '", src.camera, "'"));
  }
  if (k->has_value()) {
    out.pinhole = true;
    out.intrinsics = **k;
  }
  absl::StatusOr<std::string> bytes = store.ReadBlob(src.blob_sha256);
  if (!bytes.ok()) return bytes.status();
  absl::StatusOr<ingest::DerivedImage> image = ingest::DecodeRgbzImage(*bytes, max_pixels);
  if (!image.ok()) {
    return absl::DataLossError(
        absl::StrCat("stored image ", src.blob_sha256, ": ", image.status().message()));
  }
  out.image = std::move(*image);
  return out;
}

ingest::CameraSource StoredCamera(const store::ProjectStore& store, const store::SourceInfo& src,
                                  int32_t batch, int64_t max_pixels) {
  ingest::CameraSource cam = CameraOf(src, batch);
  const store::ProjectStore* st = &store;
  cam.load = [st, src, max_pixels]() -> absl::StatusOr<ingest::LinearImage> {
    if (absl::StatusOr<std::optional<geometry::PinholeIntrinsics>> k =
            ProjectionOfCameraText(src.camera);
        !k.ok()) {
      return absl::DataLossError(absl::StrCat("source ", src.id, ": ", k.status().message()));
    }
    absl::StatusOr<std::optional<ingest::SphereWindow>> sphere = SphereOfCameraText(src);
    absl::StatusOr<std::optional<ingest::CylinderImage>> cylinder =
        CylinderOfCameraText(src.camera);
    if (!sphere.ok() || !cylinder.ok()) {
      return absl::DataLossError(absl::StrCat(
          "source ", src.id, ": ",
          (sphere.ok() ? cylinder.status() : sphere.status()).message()));
    }
    absl::StatusOr<std::string> bytes = st->ReadBlob(src.blob_sha256);
    if (!bytes.ok()) return bytes.status();
    absl::StatusOr<ingest::LinearImage> image =
        ingest::DecodeImage(*bytes, src.modality == records::Modality::kIr, max_pixels);
    if (!image.ok()) {
      return absl::DataLossError(
          absl::StrCat("stored image ", src.blob_sha256, ": ", image.status().message()));
    }
    if (!src.mask_sha256.empty()) {  // as the ingest applied it (ingest::DecodePanorama)
      absl::StatusOr<std::string> mask = st->ReadBlob(src.mask_sha256);
      if (!mask.ok()) return mask.status();
      if (absl::Status s = ingest::ApplyMask(*mask, max_pixels, *image); !s.ok()) {
        return absl::DataLossError(
            absl::StrCat("stored mask ", src.mask_sha256, ": ", s.message()));
      }
    }
    if (*sphere || *cylinder) {  // as the ingest placed it (ingest::DecodePanorama)
      if (absl::Status s = *cylinder ? ingest::CylinderToSphere(**cylinder, max_pixels, *image)
                                     : ingest::PlaceInSphere(**sphere, max_pixels, *image);
          !s.ok()) {
        return absl::DataLossError(
            absl::StrCat("stored image ", src.blob_sha256, ": ", s.message()));
      }
    }
    return image;
  };
  return cam;
}

int64_t DecodedImageBytes(const store::SourceInfo& src) {
  const bool opaque = src.mask_sha256.empty() && !PartOfTheSphere(src);
  const int64_t floats = opaque ? 3 : 4;
  return int64_t(src.width_px) * src.height_px * floats * int64_t(sizeof(float));
}

std::string DecodedImageKey(const store::SourceInfo& src) {
  std::string key = src.mask_sha256.empty()
                        ? src.blob_sha256
                        : absl::StrCat(src.blob_sha256, " mask ", src.mask_sha256);
  if (PartOfTheSphere(src)) {
    absl::StrAppend(&key, " ", src.camera, " of ", src.width_px, "x", src.height_px);
  }
  return key;
}

absl::StatusOr<std::shared_ptr<const ingest::LidarSource>> LoadedLidar(
    const store::ProjectStore& store, const store::SourceInfo& src, int32_t batch,
    SourceImageCache* images) {
  // What the points and their gap fill depend on: the blob, the source's pose and the vossel
  // size (the cache serves every project of the engine); the id and batch its records carry.
  const double h = store.settings().vossel_size_m;
  const geometry::Pose& p = src.pose;
  const std::string key = absl::StrFormat(
      "%s lidar %d %d h %.17g o %.17g %.17g %.17g q %.17g %.17g %.17g %.17g", src.blob_sha256,
      src.id, batch, h, p.o_world.x(), p.o_world.y(), p.o_world.z(), p.q_world_sensor.w(),
      p.q_world_sensor.x(), p.q_world_sensor.y(), p.q_world_sensor.z());
  const bool caching = images != nullptr && images->budget_bytes() > 0;
  if (caching) {
    if (std::shared_ptr<const ingest::LidarSource> kept = images->FindLidar(key)) return kept;
  }
  const auto t0 = std::chrono::steady_clock::now();
  absl::StatusOr<ingest::LidarSource> lidar = LoadLidar(store, src, batch);
  if (!lidar.ok()) return lidar.status();
  lidar->gap_fill = ingest::GapFill(*lidar, h);
  auto loaded = std::make_shared<const ingest::LidarSource>(std::move(*lidar));
  if (caching) images->PutLidar(key, loaded, SecondsSince(t0));
  return loaded;
}

namespace {

// What a camera's decode and its detectors read: the blob and mask, IR or not, the pixel limit,
// and whether the image wraps (an equirect panorama) or not (a pinhole photo).
std::string CameraKey(const store::SourceInfo& src, int64_t max_pixels, bool pinhole) {
  return absl::StrCat(DecodedImageKey(src),
                      src.modality == records::Modality::kIr ? " ir " : " rgb ", max_pixels,
                      pinhole ? " pinhole" : " equirect");
}

// A camera reading an image kept as its 8-bit codes: the rows its records read are unpacked
// when they are sampled (a table lookup, where a miss decodes its file) and its channel shift
// corrected on those rows (ingest::CameraRecords), not the whole image: a revisit samples a
// few blocks of it.
void ReadCodes(std::shared_ptr<const geometry::Srgb8Image> codes,
               std::shared_ptr<const ingest::ArtefactMaps> artefacts, ingest::CameraSource& cam) {
  cam.image = codes->header;  // its size, no pixels
  cam.kept_image.reset();
  cam.load = [codes]() -> absl::StatusOr<ingest::LinearImage> {
    return geometry::UnpackSrgb8(*codes);
  };
  cam.load_rows = [codes](int row_begin, int row_end) -> absl::StatusOr<ingest::LinearImage> {
    return geometry::UnpackSrgb8Rows(*codes, row_begin, row_end);
  };
  cam.artefacts = std::move(artefacts);
}

// `decoded` as cameras share it, its artefact maps found, kept in `images` under `key` when it
// fits: as its 8-bit codes when it has them (an 8-bit file's; a quarter of the bytes), else
// with its channel shift corrected once on the whole image (CameraSource::kept_image; each
// corrected row reads the image as decoded, so its rows are those a camera's records would
// correct). With `whole` (a scan's own camera, whose records read every row) `cam` shares the
// corrected image; else (a revisit's) an 8-bit one reads the codes (ReadCodes).
void ShareDecoded(ingest::LinearImage decoded, const std::string& key, SourceImageCache& images,
                  ingest::CameraSource& cam, double decode_seconds, bool whole) {
  const auto t0 = std::chrono::steady_clock::now();
  auto artefacts = std::make_shared<const ingest::ArtefactMaps>(
      ingest::DetectArtefacts(decoded, /*wrap=*/!cam.pinhole));
  std::shared_ptr<const geometry::Srgb8Image> codes;
  if (std::optional<geometry::Srgb8Image> packed = geometry::PackSrgb8(decoded)) {
    codes = std::make_shared<const geometry::Srgb8Image>(std::move(*packed));
    images.PutPacked(key, codes, artefacts, decode_seconds + SecondsSince(t0));
    if (!whole) {
      ReadCodes(std::move(codes), std::move(artefacts), cam);
      return;
    }
  }
  ingest::CorrectChannelShift(decoded, artefacts->fringing);
  auto image = std::make_shared<const geometry::LinearImage>(std::move(decoded));
  if (codes == nullptr) images.Put(key, image, artefacts, decode_seconds + SecondsSince(t0));
  cam.kept_image = std::move(image);  // shared: the records read it, nothing writes it
  cam.artefacts = std::move(artefacts);
}

}  // namespace

absl::StatusOr<ingest::CameraSource> LoadedCamera(const store::ProjectStore& store,
                                                  const store::SourceInfo& src, int32_t batch,
                                                  int64_t max_pixels, SourceImageCache* images) {
  ingest::CameraSource cam = StoredCamera(store, src, batch, max_pixels);
  if (images == nullptr || images->budget_bytes() <= 0) return cam;
  const std::string key = CameraKey(src, max_pixels, cam.pinhole.has_value());
  std::shared_ptr<const ingest::ArtefactMaps> artefacts;
  std::shared_ptr<const geometry::LinearImage> image = images->Find(key, &artefacts);
  if (image != nullptr && artefacts != nullptr) {
    cam.kept_image = std::move(image);
    cam.artefacts = std::move(artefacts);
    return cam;
  }
  if (std::shared_ptr<const geometry::Srgb8Image> codes = images->FindPacked(key, &artefacts);
      codes != nullptr && artefacts != nullptr) {
    ReadCodes(std::move(codes), std::move(artefacts), cam);
    return cam;
  }
  const auto t0 = std::chrono::steady_clock::now();
  absl::StatusOr<ingest::LinearImage> decoded = cam.load();
  if (!decoded.ok()) return decoded.status();
  ShareDecoded(std::move(*decoded), key, *images, cam, SecondsSince(t0), /*whole=*/false);
  return cam;
}

void KeepDecodedCamera(const store::SourceInfo& src, int64_t max_pixels, SourceImageCache* images,
                       ingest::CameraSource& cam, double decode_seconds) {
  if (images == nullptr || images->budget_bytes() <= 0 || cam.image.pixels.empty() ||
      cam.kept_image != nullptr) {
    return;
  }
  ingest::LinearImage decoded = std::move(cam.image);
  cam.image = ingest::LinearImage();
  ShareDecoded(std::move(decoded), CameraKey(src, max_pixels, cam.pinhole.has_value()), *images,
               cam, decode_seconds, /*whole=*/true);
}

}  // namespace vasl::flows

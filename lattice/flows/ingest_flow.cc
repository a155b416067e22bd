// The incremental ingest flow (flows.h): a scan's own points merged into the lattice, normals
// recomputed where a neighbourhood changed, records of its own sources, and older sources
// revisited only where the new geometry reaches them (change.h).
#include <chrono>
#include <cstring>
#include <functional>
#include <future>
#include <numeric>

#include "absl/strings/str_cat.h"
#include "lattice/flows/change.h"
#include "lattice/flows/flows.h"
#include "lattice/ingest/calibration.h"
#include "lattice/ingest/validate.h"
#include "lattice/ingest/voxelise.h"
#include "lattice/tiles/tile_split.h"

namespace vasl::flows {
namespace {

/// Decoded images a scan's calibration check keeps with its cameras for their records, so that
/// a panorama is decoded once per ingest (a 4096×2048 one: 100 MB as float RGB).
constexpr int64_t kKeepDecodedBytes = int64_t{512} << 20;

// Packs LiDAR points as little-endian float32 (x, y, z, intensity), 16 bytes a point: the blob
// format of a LiDAR source (LoadLidar). A scan with a range grid appends each point's cell
// (uint32) and then the grid's rows and columns (uint32 each): 20 bytes a point and 8.
std::string PackPoints(const ingest::LidarData& lidar) {
  const size_t n = lidar.xyz_sensor_m.size() / 3;
  const bool grid = !lidar.grid_cell.empty();
  std::string bytes(n * 16 + (grid ? n * 4 + 8 : 0), '\0');
  for (size_t i = 0; i < n; ++i) {
    const float rec[4] = {lidar.xyz_sensor_m[3 * i], lidar.xyz_sensor_m[3 * i + 1],
                          lidar.xyz_sensor_m[3 * i + 2],
                          lidar.intensity.empty() ? 1.0f : lidar.intensity[i]};
    std::memcpy(&bytes[i * 16], rec, 16);
  }
  if (grid) {
    std::memcpy(&bytes[n * 16], lidar.grid_cell.data(), n * 4);
    const uint32_t shape[2] = {uint32_t(lidar.grid_rows), uint32_t(lidar.grid_columns)};
    std::memcpy(&bytes[n * 20], shape, 8);
  }
  return bytes;
}

// The scan's range grid onto one of its sources.
void SetGrid(const ingest::LidarData& lidar, ingest::LidarSource* out) {
  out->grid_rows = lidar.grid_rows;
  out->grid_columns = lidar.grid_columns;
  out->grid_cell = lidar.grid_cell;
}

}  // namespace

absl::Status CameraOnlyWithoutGeometry(const std::string& project, const std::string& scan) {
  return absl::FailedPreconditionError(absl::StrCat(
      "scan '", scan, "' has images and no LiDAR points, and project '", project,
      "' has no geometry yet: ingest a scan with LiDAR points first (a camera-only scan "
      "colours the surfaces the project already has)"));
}

absl::StatusOr<store::ScanInfo> StoreScanBlobs(store::ProjectStore& st, const ingest::ScanInput& scan,
                                               const std::vector<ingest::ImageHeader>& images) {
  auto next_source = st.NextSourceId();
  auto batch = st.NextBatchId();
  if (!next_source.ok()) return next_source.status();
  if (!batch.ok()) return batch.status();
  store::ScanInfo info;
  info.name = scan.scan_name;
  info.rig = scan.rig;
  info.captured_utc = scan.captured_utc;
  info.pose = scan.pose;
  info.batch = *batch;
  if (!scan.lidar.xyz_sensor_m.empty()) {  // none: a camera-only scan
    auto blob = st.PutBlob(PackPoints(scan.lidar));
    if (!blob.ok()) return blob.status();
    store::SourceInfo lidar;
    lidar.id = (*next_source)++;
    lidar.name = "lidar";
    lidar.modality = records::Modality::kLidar;
    lidar.pose = scan.pose;
    lidar.blob_sha256 = *blob;
    lidar.divergence_rad = scan.lidar.divergence_rad;
    lidar.point_count = int64_t(scan.lidar.xyz_sensor_m.size() / 3);
    info.sources.push_back(lidar);
    if (!scan.lidar.rgb.empty()) {  // the colour of the returns: a source of its own
      std::string colours(scan.lidar.rgb.size() * sizeof(float), '\0');
      std::memcpy(colours.data(), scan.lidar.rgb.data(), colours.size());
      auto colour_blob = st.PutBlob(colours);
      if (!colour_blob.ok()) return colour_blob.status();
      store::SourceInfo colour = lidar;
      colour.id = (*next_source)++;
      colour.name = "point-colour";
      colour.modality = records::Modality::kRgb;
      colour.blob_sha256 = *colour_blob;
      colour.camera = PointColourCameraText(lidar.blob_sha256);
      info.sources.push_back(colour);
    }
  }
  for (size_t i = 0; i < scan.panoramas.size(); ++i) {
    const ingest::PanoramaData& pano = scan.panoramas[i];
    auto blob = st.PutBlob(pano.encoded_image);
    if (!blob.ok()) return blob.status();
    if (pano.visual_reference) {  // kept with the scan, no source
      info.visual_references.push_back({pano.name, pano.pose, *blob, images[i].width_px,
                                        images[i].height_px, int64_t(pano.encoded_image.size())});
      continue;
    }
    store::SourceInfo cam;
    cam.id = (*next_source)++;
    cam.name = pano.name;
    cam.modality = pano.modality;
    cam.pose = pano.pose;
    cam.blob_sha256 = *blob;
    cam.width_px = images[i].width_px;
    cam.height_px = images[i].height_px;
    cam.divergence_rad = pano.angular_resolution_rad;
    if (pano.pinhole) cam.camera = DerivedCameraText(true, *pano.pinhole, 0);
    if (pano.sphere) cam.camera = SphereCameraText(*pano.sphere);
    if (pano.cylinder) cam.camera = CylinderCameraText(*pano.cylinder);
    if (!pano.encoded_mask.empty()) {
      auto mask = st.PutBlob(pano.encoded_mask);
      if (!mask.ok()) return mask.status();
      cam.mask_sha256 = *mask;
    }
    info.sources.push_back(cam);
  }
  return info;
}

absl::StatusOr<FlowResult> IngestScan(store::ProjectStore& store, const store::Snapshot& head,
                                      const store::ScanInfo& info, const ingest::ScanInput& scan,
                                      int64_t max_image_pixels, const StageFn& stage,
                                      SourceImageCache* images) {
  const ingest::LidarData& lidar = scan.lidar;
  FlowResult result;
  internal::StageClock clock(result, stage);
  const double h = store.settings().vossel_size_m;
  const int T = store.settings().tile_vossels;

  // The scan's sources as the stages consume them.
  internal::Change change;
  size_t next_image = 0;
  for (const store::SourceInfo& src : info.sources) {
    if (src.modality == records::Modality::kLidar) {
      ingest::LidarSource l = LidarOf(src, info.batch);
      l.xyz_sensor_m = lidar.xyz_sensor_m;
      l.intensity = lidar.intensity;
      SetGrid(lidar, &l);
      change.new_sources.lidars.push_back(std::move(l));
    } else if (IsPointColour(src)) {
      ingest::LidarSource c = LidarOf(src, info.batch);
      c.xyz_sensor_m = lidar.xyz_sensor_m;
      c.rgb = lidar.rgb;
      SetGrid(lidar, &c);  // its gap fill is sampled like the LiDAR's (as LoadPointColour has it)
      c.colour_id = src.id;
      change.new_sources.point_colours.push_back(std::move(c));
    } else {
      while (next_image < scan.panoramas.size() && scan.panoramas[next_image].visual_reference) {
        ++next_image;  // kept with the scan, no camera source
      }
      if (next_image >= scan.panoramas.size()) {
        return absl::InternalError("IngestScan: fewer panoramas than camera sources");
      }
      ingest::CameraSource cam = CameraOf(src, info.batch);
      cam.load = [&scan, i = next_image++, max_image_pixels] {
        return ingest::DecodePanorama(scan, i, max_image_pixels);
      };
      change.new_sources.cameras.push_back(std::move(cam));
    }
  }
  if (change.new_sources.lidars.size() > 1) {
    return absl::InternalError("IngestScan: a scan has at most one LiDAR source");
  }

  // The first camera's image, decoded on a thread of its own while the returns are binned and
  // their normals found (PNG and JPEG decoders run on one core; the stages before calibration
  // keep the others busy). Every other image is decoded where it is needed. The future is
  // waited for on every way out of this function, the scan it reads outliving it.
  struct Decoded {
    absl::StatusOr<ingest::LinearImage> image;
    double seconds = 0.0;
  };
  const auto decode = [](const std::function<absl::StatusOr<ingest::LinearImage>()>& load) {
    const auto t0 = std::chrono::steady_clock::now();
    Decoded d{load()};
    d.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    return d;
  };
  std::future<Decoded> first_image;
  if (!change.new_sources.lidars.empty() && !change.new_sources.cameras.empty()) {
    first_image = std::async(std::launch::async, decode, change.new_sources.cameras[0].load);
  }

  store::CommitPlan plan;
  if (change.new_sources.lidars.empty()) {
    // A camera-only scan: the geometry stays as it is; its cameras colour what they see of it.
    change.geometry = head.geometry;
    change.old_to_new.resize(head.geometry.size());
    std::iota(change.old_to_new.begin(), change.old_to_new.end(), 0);
  } else {
    // §1: bin the scan's own returns and merge them (exact sums), then derive.
    if (absl::Status stop = clock.Start("voxelise", 0.2); !stop.ok()) return stop;
    absl::StatusOr<ingest::BinnedLidar> binned = ingest::BinLidar(change.new_sources.lidars[0], h);
    if (!binned.ok()) return binned.status();
    // The gap fill binned here is what the LiDAR's and its colour's records sample.
    change.new_sources.lidars[0].gap_fill = binned->fill;
    for (ingest::LidarSource& c : change.new_sources.point_colours) c.gap_fill = binned->fill;
    const records::VosselGeometry empty =
        head.geometry.size() == 0 ? ingest::EmptyGeometry(h) : records::VosselGeometry{};
    ingest::MergeResult merged = ingest::MergeBinned(
        head.geometry.size() == 0 ? empty : head.geometry, *binned, &change.geometry);
    // The vossels the scan left alone keep their centroids and covariances (the same bits).
    records::DeriveCentroidAndCovariance(change.geometry, &merged.touched);
    change.old_to_new = std::move(merged.old_to_new);

    // Normals where a neighbourhood changed: the touched vossels and their 26 neighbours.
    if (absl::Status stop = clock.Start("normals", 0.35); !stop.ok()) return stop;
    std::vector<uint8_t> renormal(change.geometry.size(), 0);
    {
      auto acc = change.geometry.index_grid->getConstAccessor();
      for (size_t v = 0; v < merged.touched.size(); ++v) {
        if (!merged.touched[v]) continue;
        const openvdb::Coord c = change.geometry.coord[v];
        for (int dx = -1; dx <= 1; ++dx)
          for (int dy = -1; dy <= 1; ++dy)
            for (int dz = -1; dz <= 1; ++dz) {
              int32_t n;
              if (acc.probeValue(c.offsetBy(dx, dy, dz), n)) renormal[size_t(n)] = 1;
            }
      }
    }
    ingest::ComputeNormals(change.geometry, &renormal);
    std::set<tiles::TileKey>& returns = plan.source_tiles[change.new_sources.lidars[0].id];
    for (const openvdb::Coord& c : binned->coord) returns.insert(tiles::TileOf(c, T));
    for (const ingest::LidarSource& c : change.new_sources.point_colours) {
      plan.source_tiles[c.colour_id] = returns;  // its records lie where the returns do
    }
  }

  plan.made_by = absl::StrCat("ingest scan ", info.name);
  plan.add_scan = info;

  // §2.3: each camera against the scan's own LiDAR, before its colours are fused. The decoded
  // image stays with the camera for its records (Propagate frees it once they are sampled)
  // while the scan's kept images fit kKeepDecodedBytes; a camera beyond it decodes again. A
  // kept image goes to the revisit cache too, as a revisit would decode it (KeepDecodedCamera).
  if (!change.new_sources.lidars.empty()) {
    const ingest::LidarSource& l = change.new_sources.lidars[0];
    int64_t kept_bytes = 0;
    for (size_t k = 0; k < change.new_sources.cameras.size(); ++k) {
      ingest::CameraSource& cam = change.new_sources.cameras[k];
      const double fraction = 0.35 + 0.1 * double(k) / double(change.new_sources.cameras.size());
      if (absl::Status stop = clock.Start(absl::StrCat("calibration of source ", cam.id), fraction);
          !stop.ok()) {
        return stop;
      }
      Decoded decoded = k == 0 && first_image.valid() ? first_image.get() : decode(cam.load);
      absl::StatusOr<ingest::LinearImage>& image = decoded.image;
      if (!image.ok()) return image.status();
      const double decode_seconds = decoded.seconds;
      records::CalibrationHealth health = ingest::CheckCalibration(l, cam, *image);
      const store::SourceInfo* info = nullptr;
      for (store::SourceInfo& src : plan.add_scan->sources) {
        if (src.id != cam.id) continue;
        result.calibration.emplace_back(src.name, health);
        src.calibration = std::move(health);
        info = &src;
      }
      const int64_t bytes = int64_t(image->pixels.size() * sizeof(float));
      if (cam.image.pixels.empty() && kept_bytes + bytes <= kKeepDecodedBytes) {
        kept_bytes += bytes;
        cam.image = std::move(*image);
        // Shared with the revisit cache: the next ingest revisits this camera first.
        if (info != nullptr) {
          KeepDecodedCamera(*info, max_image_pixels, images, cam, decode_seconds);
        }
      }
    }
  }

  absl::StatusOr<std::vector<store::ScanInfo>> scans = store.ListScans(head.version);
  if (!scans.ok()) return scans.status();
  if (head.version == 0) scans->clear();

  absl::StatusOr<store::Snapshot> next =
      internal::Propagate(store, head, std::move(change), internal::SourcesOf(*scans),
                          max_image_pixels, images, plan, result, clock);
  if (!next.ok()) return next.status();
  if (absl::Status s = internal::CommitFlow(store, std::move(*next), plan, result, clock); !s.ok()) {
    return s;
  }
  return result;
}

}  // namespace vasl::flows

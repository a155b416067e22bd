// Claims of a camera image with an alpha channel (a stitcher's transparent nadir, a masked rig
// or operator): a transparent pixel is one the camera does not report. The decoder keeps the
// coverage and associates the colour with it after linearisation; a record whose sample lies
// mostly on uncovered pixels is invalidated (no weight, §7's gate), one mostly covered takes the
// colour of the covered part alone, and one wholly covered is the record the opaque image gives.
// Whatever colour a transparent pixel carries never reaches a record.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <map>
#include <optional>
#include <string>
#include <tuple>
#include <vector>

#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include "lattice/engine.h"
#include "lattice/geometry/linear_image.h"
#include "lattice/ingest/artefacts.h"
#include "lattice/ingest/sources.h"
#include "lattice/render/render.h"
#include "lattice/store/project_store.h"
#include "tests/scenes/synthetic_scene.h"

namespace vasl {
namespace {
namespace fs = std::filesystem;

constexpr int kPanoW = 512, kPanoH = 256;

// `channels` values per pixel (W×H, linear, the last one alpha when `channels` is 2 or 4)
// encoded as `file_name`'s format: 8-bit colour codes through the sRGB curve and alpha codes
// round(a·255) (a PNG's unassociated colour; every value so with `mask`), or floats as they
// are (an EXR's: the caller associates them).
std::string Encode(const std::vector<float>& values, int w, int h, int channels,
                   const std::string& file_name, OIIO::TypeDesc type, bool mask = false) {
  std::vector<unsigned char> buffer;
  OIIO::Filesystem::IOVecOutput proxy(buffer);
  auto out = OIIO::ImageOutput::create(file_name, &proxy);
  EXPECT_TRUE(out != nullptr) << OIIO::geterror();
  if (!out) return {};
  OIIO::ImageSpec spec(w, h, channels, type);
  if (channels == 2 || channels == 4) spec.alpha_channel = channels - 1;
  if (type == OIIO::TypeDesc::UINT8) spec.attribute("oiio:UnassociatedAlpha", 1);
  std::vector<unsigned char> pixels(values.size() * type.size());
  for (size_t i = 0; i < values.size(); ++i) {
    const bool alpha =
        mask || ((channels == 2 || channels == 4) && int(i % channels) == channels - 1);
    if (type == OIIO::TypeDesc::UINT8) {
      const float v = std::clamp(values[i], 0.0f, 1.0f);
      pixels[i] = alpha ? uint8_t(std::lround(v * 255.0f)) : geometry::LinearToSrgb8(v);
    } else {
      std::memcpy(&pixels[4 * i], &values[i], 4);
    }
  }
  const bool ok = out->open(file_name, spec) && out->write_image(type, pixels.data()) &&
                  out->close();
  EXPECT_TRUE(ok) << out->geterror();
  return std::string(buffer.begin(), buffer.end());
}

TEST(AlphaMaskTest, DecodeKeepsCoverageAndAssociatesColourAfterLinearising) {
  // 2×1 RGBA: one pixel half covered, one whole.
  const std::vector<float> rgba = {0.5f, 0.2f, 0.05f, 128.0f / 255.0f, 0.3f, 0.6f, 0.9f, 1.0f};
  absl::StatusOr<geometry::LinearImage> png = ingest::DecodeImage(
      Encode(rgba, 2, 1, 4, "a.png", OIIO::TypeDesc::UINT8), false, 1 << 20);
  ASSERT_TRUE(png.ok()) << png.status();
  ASSERT_EQ(png->channels, 3);
  ASSERT_EQ(png->alpha.size(), 2u);
  EXPECT_FLOAT_EQ(png->alpha[0], 128.0f / 255.0f);  // alpha codes are linear
  EXPECT_EQ(png->alpha[1], 1.0f);
  for (int c = 0; c < 3; ++c) {
    // The sRGB code's linear value times the coverage (OpenImageIO's own association would
    // multiply the code before the curve: 0.5 · 0.50 became 0.19, not 0.25).
    const float linear = geometry::Srgb8ToLinear()[geometry::LinearToSrgb8(rgba[size_t(c)])];
    EXPECT_FLOAT_EQ(png->pixels[size_t(c)], linear * (128.0f / 255.0f)) << "channel " << c;
    const float whole = geometry::Srgb8ToLinear()[geometry::LinearToSrgb8(rgba[size_t(4 + c)])];
    EXPECT_EQ(png->pixels[size_t(3 + c)], whole);
  }
  // The half-covered pixel read alone is its own colour again.
  float read[3];
  geometry::SampleBilinear(*png, 0.5, 0.5, false, read);
  const float a = geometry::SampleCoverage(*png, 0.5, 0.5, false);
  EXPECT_NEAR(read[0] / a, geometry::Srgb8ToLinear()[geometry::LinearToSrgb8(0.5f)], 1e-6);

  // An EXR's colour is associated already: kept as it is.
  std::vector<float> assoc = rgba;
  for (int c = 0; c < 3; ++c) assoc[size_t(c)] *= assoc[3];
  absl::StatusOr<geometry::LinearImage> exr = ingest::DecodeImage(
      Encode(assoc, 2, 1, 4, "a.exr", OIIO::TypeDesc::FLOAT), false, 1 << 20);
  ASSERT_TRUE(exr.ok()) << exr.status();
  ASSERT_EQ(exr->alpha.size(), 2u);
  for (int c = 0; c < 3; ++c) EXPECT_EQ(exr->pixels[size_t(c)], assoc[size_t(c)]);

  // Gray with alpha: the gray replicated, the alpha kept.
  absl::StatusOr<geometry::LinearImage> gray = ingest::DecodeImage(
      Encode({0.4f, 0.0f, 0.7f, 1.0f}, 2, 1, 2, "g.png", OIIO::TypeDesc::UINT8), false,
      1 << 20);
  ASSERT_TRUE(gray.ok()) << gray.status();
  ASSERT_EQ(gray->alpha.size(), 2u);
  EXPECT_EQ(gray->alpha[0], 0.0f);
  EXPECT_EQ(gray->pixels[0], 0.0f);  // uncovered: no colour
  EXPECT_EQ(gray->pixels[3], gray->pixels[5]);

  // Alpha that covers every pixel keeps no coverage: the image is the opaque one.
  absl::StatusOr<geometry::LinearImage> opaque = ingest::DecodeImage(
      Encode({0.5f, 0.2f, 0.05f, 1.0f}, 1, 1, 4, "o.png", OIIO::TypeDesc::UINT8), false, 1 << 20);
  ASSERT_TRUE(opaque.ok()) << opaque.status();
  EXPECT_TRUE(opaque->alpha.empty());
  EXPECT_TRUE(geometry::PackSrgb8(*opaque).has_value());
}

struct Rgb {
  float v[3];
  bool invalid;
};
using RecordsByVossel = std::map<std::tuple<int, int, int>, Rgb>;
struct Ingested {
  RecordsByVossel records;
  render::RenderImage detail;  ///< a novel view coloured from the source image (§8)
};

// The RGB records of version `version` of a stored project, by vossel.
RecordsByVossel RgbRecordsAt(const store::ProjectStore& st, int64_t version) {
  RecordsByVossel out;
  auto snap = st.LoadSnapshot(version);
  EXPECT_TRUE(snap.ok()) << snap.status();
  if (!snap.ok()) return out;
  const records::RecordSet& rec = (*snap)->records;
  for (size_t i = 0; i < rec.size(); ++i) {
    if (rec.modality[i] != int8_t(records::Modality::kRgb)) continue;
    const openvdb::Coord c = (*snap)->geometry.coord[size_t(rec.vossel[i])];
    Rgb& v = out[{c.x(), c.y(), c.z()}];
    for (int k = 0; k < 3; ++k) v.v[k] = rec.value[records::kValueChannels * i + size_t(k)];
    v.invalid = (rec.flags[i] & records::kFlagInvalidated) != 0;
  }
  return out;
}

// The records of `a` that `b` lacks or holds otherwise (another value, bit for bit, or flag).
size_t Differing(const RecordsByVossel& a, const RecordsByVossel& b) {
  size_t differ = 0;
  for (const auto& [key, r] : a) {
    auto it = b.find(key);
    differ += it == b.end() || it->second.invalid != r.invalid ||
              std::memcmp(it->second.v, r.v, sizeof r.v) != 0;
  }
  return differ;
}

size_t Invalidated(const RecordsByVossel& records) {
  size_t n = 0;
  for (const auto& [key, r] : records) n += r.invalid;
  return n;
}

// A project at `root` holding station 0's LiDAR and `pano` (named cam0, posed at the station's
// camera; its image, mask, sphere or cylinder as given) as its panorama: its RGB records, and a
// render from 30 cm beside the camera with colour read from the image. `rebuild`: the project
// is rebuilt from its blobs too, and the rebuild must give the same records (StoredCamera reads
// the image back as the ingest decoded it).
Ingested IngestCamera(const fs::path& root, const scenes::SyntheticRoom& room,
                      ingest::PanoramaData pano, bool rebuild = false) {
  Ingested ingested;
  fs::remove_all(root);
  auto engine = Engine::Open(root);
  EXPECT_TRUE(engine.ok()) << engine.status();
  if (!engine.ok()) return ingested;
  store::ProjectSettings settings;
  settings.vossel_size_m = 0.05;
  EXPECT_TRUE((*engine)->CreateProject("p", settings).ok());
  auto scan = scenes::MakeScanInput(room, 0, scenes::LidarSettings::Small(1), 0);
  EXPECT_TRUE(scan.ok()) << scan.status();
  if (!scan.ok()) return ingested;
  pano.name = "cam0";
  pano.pose = scenes::CameraPoseForStation(room.Stations()[0]);
  scan->panoramas.push_back(pano);
  auto r = (*engine)->IngestScan("p", *scan);
  EXPECT_TRUE(r.ok()) << r.status();
  if (!r.ok()) return ingested;
  render::RenderRequest request;
  request.pose = pano.pose;
  request.pose.o_world += Eigen::Vector3d(0.3, 0.0, 0.0);
  request.width_px = kPanoW;
  request.height_px = kPanoH;
  request.colour_detail = render::ColourDetail::kSourceImages;
  auto rendered = (*engine)->Render("p", request);
  EXPECT_TRUE(rendered.ok()) << rendered.status();
  if (rendered.ok()) ingested.detail = std::move(*rendered);
  if (rebuild) {
    auto rebuilt = (*engine)->Rebuild("p");
    EXPECT_TRUE(rebuilt.ok()) << rebuilt.status();
  }
  auto st = store::ProjectStore::Open(root / "p");
  EXPECT_TRUE(st.ok()) << st.status();
  if (!st.ok()) return ingested;
  ingested.records = RgbRecordsAt(**st, r->version);
  if (rebuild) {
    const RecordsByVossel again = RgbRecordsAt(**st, (*st)->head_version());
    EXPECT_EQ(again.size(), ingested.records.size());
    EXPECT_EQ(Differing(ingested.records, again), 0u)
        << "the rebuild from the stored image differs from the ingest";
  }
  fs::remove_all(root);
  return ingested;
}

Ingested RgbRecords(const fs::path& root, const scenes::SyntheticRoom& room,
                    const std::string& image, const std::string& mask = "") {
  ingest::PanoramaData pano;
  pano.encoded_image = image;
  pano.encoded_mask = mask;
  return IngestCamera(root, room, pano);
}

// Sends station 0's scan with each panorama of `cases` (named cam0, posed at the station's
// camera) to a new project at `root`: each must be refused as INVALID_ARGUMENT naming cam0 and
// saying its text, and nothing be stored.
void ExpectRefused(const fs::path& root, const scenes::SyntheticRoom& room,
                   const std::vector<std::pair<ingest::PanoramaData, std::string>>& cases) {
  fs::remove_all(root);
  auto engine = Engine::Open(root);
  ASSERT_TRUE(engine.ok()) << engine.status();
  store::ProjectSettings settings;
  settings.vossel_size_m = 0.05;
  ASSERT_TRUE((*engine)->CreateProject("p", settings).ok());
  auto scan = scenes::MakeScanInput(room, 0, scenes::LidarSettings::Small(1), 0);
  ASSERT_TRUE(scan.ok()) << scan.status();
  for (const auto& [pano, says] : cases) {
    ingest::ScanInput sent = *scan;
    sent.panoramas = {pano};
    sent.panoramas[0].name = "cam0";
    sent.panoramas[0].pose = scenes::CameraPoseForStation(room.Stations()[0]);
    auto r = (*engine)->IngestScan("p", sent);
    ASSERT_FALSE(r.ok());
    EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument) << r.status();
    EXPECT_NE(r.status().message().find("'cam0'"), std::string::npos) << r.status();
    EXPECT_NE(r.status().message().find(says), std::string::npos) << r.status();
    std::printf("refused: %s\n", std::string(r.status().message()).c_str());
  }
  auto st = store::ProjectStore::Open(root / "p");
  ASSERT_TRUE(st.ok()) << st.status();
  EXPECT_EQ((*st)->head_version(), 0);
  fs::remove_all(root);
}

TEST(AlphaMaskTest, TransparentPixelsGiveNoColourAndCoveredOnesTheirOwn) {
  const scenes::SyntheticRoom room = scenes::SyntheticRoom::Default();
  const scenes::Panorama seen = scenes::RenderPanorama(
      room, scenes::CameraPoseForStation(room.Stations()[0]), kPanoW, kPanoH, 2);
  // The nadir masked as a stitcher masks its tripod: transparent from row 0.7·H down, alpha
  // ramping from 1 to 0 over the 8 rows above (an anti-aliased edge), magenta under the
  // transparent pixels (what a stitcher leaves there is anyone's guess).
  const int ramp_end = int(0.7 * kPanoH), ramp_begin = ramp_end - 8;
  auto alpha_of_row = [&](int j) {
    if (j < ramp_begin) return 1.0f;
    if (j >= ramp_end) return 0.0f;
    return float(ramp_end - j) / float(ramp_end - ramp_begin + 1);
  };
  const size_t n = size_t(kPanoW) * kPanoH;
  std::vector<float> opaque(n * 3), unassociated(n * 4), associated(n * 4);
  for (size_t p = 0; p < n; ++p) {
    const float a = alpha_of_row(int(p / kPanoW));
    for (int c = 0; c < 3; ++c) {
      const float v = seen.rgb[3 * p + size_t(c)];
      opaque[3 * p + size_t(c)] = v;
      unassociated[4 * p + size_t(c)] = a > 0.0f ? v : (c == 1 ? 0.0f : 1.0f);
      associated[4 * p + size_t(c)] = v * a;
    }
    unassociated[4 * p + 3] = associated[4 * p + 3] = a;
  }
  const fs::path root = fs::temp_directory_path() / ("vasl-alpha-" + std::to_string(::getpid()));
  const Ingested plain_project =
      RgbRecords(root, room, Encode(opaque, kPanoW, kPanoH, 3, "o.png", OIIO::TypeDesc::UINT8));
  const Ingested masked_project = RgbRecords(
      root, room, Encode(unassociated, kPanoW, kPanoH, 4, "m.png", OIIO::TypeDesc::UINT8));
  const RecordsByVossel as_exr = RgbRecords(
      root, room, Encode(associated, kPanoW, kPanoH, 4, "m.exr", OIIO::TypeDesc::FLOAT)).records;
  const RecordsByVossel& plain = plain_project.records;
  const RecordsByVossel& masked = masked_project.records;
  ASSERT_GT(plain.size(), 10000u);

  // Where each record of the opaque image sampled, from the records themselves: the vossels
  // whose records match bit for bit are those wholly on covered pixels.
  size_t same = 0, invalidated = 0, partial = 0, plain_invalid = 0, exr_flipped = 0;
  double worst_partial = 0.0, worst_exr = 0.0;
  for (const auto& [key, p] : plain) {
    plain_invalid += p.invalid;
    auto m = masked.find(key);
    ASSERT_NE(m, masked.end());  // the records exist (V > 0); their weight is what changes
    if (m->second.invalid && !p.invalid) {
      ++invalidated;
      continue;
    }
    double d = 0.0;
    for (int c = 0; c < 3; ++c) d = std::max(d, double(std::abs(m->second.v[c] - p.v[c])));
    if (d == 0.0) {
      ++same;
    } else {
      ++partial;
      worst_partial = std::max(worst_partial, d);
    }
    auto e = as_exr.find(key);
    ASSERT_NE(e, as_exr.end());
    // Alpha as 8-bit codes or as floats: a kernel covered within a code of half flips.
    if (e->second.invalid != m->second.invalid) {
      ++exr_flipped;
      continue;
    }
    for (int c = 0; c < 3; ++c) {
      worst_exr = std::max(worst_exr, double(std::abs(e->second.v[c] - m->second.v[c])));
    }
  }
  std::printf("RGB records %zu: %zu as the opaque image's, %zu invalidated (on transparent "
              "pixels), %zu partly covered (max |Δ| %.4f); float EXR against PNG max |Δ| %.4f, %zu "
              "invalidated in one of the two\n",
              plain.size(), same, invalidated, partial, worst_partial, worst_exr, exr_flipped);
  EXPECT_EQ(plain_invalid, 0u);
  // The nadir below -36° holds the floor around the station: thousands of vossels.
  EXPECT_GT(invalidated, 1000u);
  EXPECT_GT(same, plain.size() / 2);
  // A partly covered record's colour is the covered part's: the albedo changes by < 0.08 over
  // 5 cm (synthetic_scene.cc) and a kernel spans a few centimetres, so it lies within 0.04 of
  // the whole kernel's. (Read as OpenImageIO associates a PNG's colour, its codes times alpha
  // before the sRGB curve, with no coverage kept, the transparent floor came out black: 0.854
  // off, none invalidated, and the EXR 0.214 from the PNG.)
  EXPECT_LE(worst_partial, 0.04);
  // 8-bit sRGB codes against floats: half a code at the top of the curve and a half-float step.
  EXPECT_LE(worst_exr, 0.0045 + 0x1p-11);
  EXPECT_LE(exr_flipped, invalidated / 100);

  // The render's colour detail reads the image where each ray hits: where that read is mostly
  // uncovered it keeps the record's colour, else the covered part's. So a pixel with colour in
  // both renders is within the same 0.04 where it read the image, and within a vossel's own
  // spread of the albedo (0.08 over 5 cm, and its kernel's blur) where it took the record's
  // colour: a few pixels along the mask's edge. The floor under the mask has none.
  const render::RenderImage& a = plain_project.detail;
  const render::RenderImage& b = masked_project.detail;
  ASSERT_EQ(a.alpha.size(), b.alpha.size());
  ASSERT_GT(a.alpha.size(), 0u);
  size_t both = 0, only_plain = 0, beyond = 0;
  double worst_pixel = 0.0;
  for (size_t p = 0; p < a.alpha.size(); ++p) {
    EXPECT_FALSE(b.alpha[p] > 0.0f && !(a.alpha[p] > 0.0f)) << "pixel " << p;
    if (!(b.alpha[p] > 0.0f)) {
      only_plain += a.alpha[p] > 0.0f;
      continue;
    }
    ++both;
    double d = 0.0;
    for (int c = 0; c < 3; ++c) {
      d = std::max(d, double(std::abs(b.rgb[3 * p + size_t(c)] - a.rgb[3 * p + size_t(c)])));
    }
    worst_pixel = std::max(worst_pixel, d);
    beyond += d > 0.04;
  }
  std::printf("colour-detail render: %zu pixels coloured in both, %zu only without the mask, "
              "max |Δ| %.4f, %zu beyond 0.04\n", both, only_plain, worst_pixel, beyond);
  EXPECT_GT(only_plain, 1000u);
  EXPECT_LE(beyond, both / 1000);
  EXPECT_LE(worst_pixel, 0.15);
}

// Claim (ingest::ApplyMask): a rig's mask sent beside an opaque image is that image's alpha: the
// same records, bit for bit, as the image sent with the mask's codes as its alpha channel; a
// 0/1 mask means what a 0/255 one does (scaled by its largest value, as an E57 imageMask's
// non-zero pixels are the valid ones); a mask of another size, or bytes that are no image,
// are refused before anything is stored.
TEST(AlphaMaskTest, AMaskBesideTheImageIsItsAlpha) {
  const scenes::SyntheticRoom room = scenes::SyntheticRoom::Default();
  const scenes::Panorama seen = scenes::RenderPanorama(
      room, scenes::CameraPoseForStation(room.Stations()[0]), kPanoW, kPanoH, 2);
  const size_t n = size_t(kPanoW) * kPanoH;
  // The mask: the nadir from row 0.7·H, an anti-aliased edge of 8 rows above it.
  std::vector<float> coverage(n), rgba(n * 4), opaque(seen.rgb.begin(), seen.rgb.end());
  const int ramp_end = int(0.7 * kPanoH);
  for (size_t p = 0; p < n; ++p) {
    const int j = int(p / kPanoW);
    coverage[p] = j >= ramp_end ? 0.0f : j < ramp_end - 8 ? 1.0f : float(ramp_end - j) / 9.0f;
    for (int c = 0; c < 3; ++c) rgba[4 * p + size_t(c)] = seen.rgb[3 * p + size_t(c)];
    rgba[4 * p + 3] = coverage[p];
  }
  std::vector<float> binary(n);
  for (size_t p = 0; p < n; ++p) binary[p] = coverage[p] > 0.5f ? 1.0f / 255.0f : 0.0f;  // codes 0/1
  std::vector<float> binary_255(n);
  for (size_t p = 0; p < n; ++p) binary_255[p] = coverage[p] > 0.5f ? 1.0f : 0.0f;
  const fs::path root = fs::temp_directory_path() / ("vasl-mask-" + std::to_string(::getpid()));
  const std::string image = Encode(opaque, kPanoW, kPanoH, 3, "o.png", OIIO::TypeDesc::UINT8);
  const RecordsByVossel with_alpha =
      RgbRecords(root, room, Encode(rgba, kPanoW, kPanoH, 4, "a.png", OIIO::TypeDesc::UINT8))
          .records;
  const RecordsByVossel with_mask =
      RgbRecords(root, room, image,
                 Encode(coverage, kPanoW, kPanoH, 1, "m.png", OIIO::TypeDesc::UINT8, true))
          .records;
  const RecordsByVossel with_01 =
      RgbRecords(root, room, image,
                 Encode(binary, kPanoW, kPanoH, 1, "m01.png", OIIO::TypeDesc::UINT8, true))
          .records;
  const RecordsByVossel with_0255 =
      RgbRecords(root, room, image,
                 Encode(binary_255, kPanoW, kPanoH, 1, "m255.png", OIIO::TypeDesc::UINT8, true))
          .records;
  ASSERT_GT(with_alpha.size(), 10000u);
  auto same = [](const RecordsByVossel& a, const RecordsByVossel& b, const char* what) {
    const size_t differ = Differing(a, b), invalid = Invalidated(a);
    std::printf("%s: %zu records, %zu invalidated, %zu differ\n", what, a.size(), invalid, differ);
    EXPECT_EQ(a.size(), b.size()) << what;
    EXPECT_EQ(differ, 0u) << what;
    EXPECT_GT(invalid, 1000u) << what;
  };
  // The mask's 8-bit codes are the alpha channel's codes, read alike: the same image.
  same(with_alpha, with_mask, "mask beside the image vs the image's own alpha");
  same(with_01, with_0255, "a 0/1 mask vs a 0/255 one");

  // Refused, and nothing stored.
  ingest::PanoramaData half_mask, no_mask;
  half_mask.encoded_image = no_mask.encoded_image = image;
  half_mask.encoded_mask = Encode(std::vector<float>(n / 4, 1.0f), kPanoW / 2, kPanoH / 2, 1,
                                  "h.png", OIIO::TypeDesc::UINT8, true);
  no_mask.encoded_mask = "not an image at all";
  ExpectRefused(root, room, {{half_mask, "'cam0': its mask"}, {no_mask, "'cam0': its mask"}});
}

// A panorama of part of the sphere (a camera without a nadir, an E57 spherical image of less
// than 360°×180°) sent with its place in the sphere is the whole sphere's panorama with the
// rest uncovered: the records of the part sent with its window equal, bit for bit, those of
// the full-size image whose pixels outside the part are transparent (alpha 0).
TEST(AlphaMaskTest, APartOfTheSphereIsItsPanoramaWithTheRestUncovered) {
  const scenes::SyntheticRoom room = scenes::SyntheticRoom::Default();
  const scenes::Panorama seen = scenes::RenderPanorama(
      room, scenes::CameraPoseForStation(room.Stations()[0]), kPanoW, kPanoH, 2);
  const fs::path root = fs::temp_directory_path() / ("vasl-sphere-" + std::to_string(::getpid()));
  struct Part {
    const char* what;
    int left, top, w, h;
  };
  for (const Part& part : {Part{"no nadir: the top 70% of the rows", 0, 0, kPanoW, 179},
                           Part{"a centred 270°x135° part", 64, 32, 384, 192}}) {
    std::vector<float> crop(size_t(part.w) * part.h * 3), rgba(size_t(kPanoW) * kPanoH * 4);
    for (int j = 0; j < kPanoH; ++j) {
      for (int i = 0; i < kPanoW; ++i) {
        const size_t p = size_t(j) * kPanoW + size_t(i);
        const bool inside = i >= part.left && i < part.left + part.w && j >= part.top &&
                            j < part.top + part.h;
        for (int c = 0; c < 3; ++c) {
          rgba[4 * p + size_t(c)] = seen.rgb[3 * p + size_t(c)];
          if (inside) {
            crop[(size_t(j - part.top) * size_t(part.w) + size_t(i - part.left)) * 3 +
                 size_t(c)] = seen.rgb[3 * p + size_t(c)];
          }
        }
        rgba[4 * p + 3] = inside ? 1.0f : 0.0f;
      }
    }
    ingest::PanoramaData part_sent;
    part_sent.encoded_image = Encode(crop, part.w, part.h, 3, "c.png", OIIO::TypeDesc::UINT8);
    part_sent.sphere = ingest::SphereWindow{kPanoW, kPanoH, part.left, part.top};
    const RecordsByVossel placed = IngestCamera(root, room, part_sent).records;
    const RecordsByVossel padded =
        RgbRecords(root, room, Encode(rgba, kPanoW, kPanoH, 4, "p.png", OIIO::TypeDesc::UINT8))
            .records;
    const size_t differ = Differing(padded, placed), invalid = Invalidated(padded);
    std::printf("%s: %zu records, %zu invalidated (outside the part), %zu differ\n", part.what,
                padded.size(), invalid, differ);
    ASSERT_GT(padded.size(), 10000u);
    EXPECT_EQ(placed.size(), padded.size()) << part.what;
    EXPECT_EQ(differ, 0u) << part.what;
    EXPECT_GT(invalid, 1000u) << part.what;
  }

  // Refused, naming the panorama, and nothing stored: a part that does not lie in its sphere,
  // a sphere that is not 2:1, a sphere for a pinhole photo, a cylinder with a sphere, a
  // cylinder that is not one.
  ingest::PanoramaData grey;
  grey.encoded_image = Encode(std::vector<float>(size_t(384) * 192 * 3, 0.5f), 384, 192, 3,
                              "g.png", OIIO::TypeDesc::UINT8);
  ingest::PanoramaData off = grey, square = grey, pinhole = grey, both = grey, flat = grey;
  off.sphere = ingest::SphereWindow{512, 256, 200, 0};
  square.sphere = ingest::SphereWindow{512, 512, 0, 0};
  pinhole.sphere = ingest::SphereWindow{512, 256, 0, 0};
  pinhole.pinhole = geometry::PinholeIntrinsics{};
  pinhole.pinhole->fx_px = pinhole.pinhole->fy_px = 300.0;
  both.sphere = ingest::SphereWindow{512, 256, 0, 0};
  both.cylinder = ingest::CylinderImage{2 * M_PI / 512, 0.01, 1.0, 96.0};
  flat.cylinder = ingest::CylinderImage{2 * M_PI / 512, 0.0, 1.0, 96.0};
  ingest::PanoramaData fine = grey;  // a pitch whose sphere would overflow its row count
  fine.cylinder = ingest::CylinderImage{1e-9, 0.01, 1.0, 96.0};
  ExpectRefused(root, room,
                {{off, "does not lie within its 512x256 sphere"},
                 {square, "width must be twice its height"},
                 {pinhole, "a pinhole photo has no sphere"},
                 {both, "neither a pinhole photo nor given a sphere window"},
                 {flat, "pixel_height_m and radius_m > 0"},
                 {fine, "more than 2^20 rows"}});
}

// A JPEG panorama of part of the sphere keeps its codec's blocks where the file had them: the
// §9 codec map of the image placed in its sphere is, inside the part, the map of the part
// decoded alone (bit for bit), and 1 outside it; read from the placed image's corner instead,
// the blocks would be misaligned (the part starts 3 and 5 pixels off the 8-pixel grid).
TEST(AlphaMaskTest, APlacedJpegKeepsItsCodecBlocks) {
  const scenes::SyntheticRoom room = scenes::SyntheticRoom::Default();
  const scenes::Panorama seen = scenes::RenderPanorama(
      room, scenes::CameraPoseForStation(room.Stations()[0]), kPanoW, kPanoH, 2);
  const int w = 400, h = 200, left = 59, top = 29;
  std::vector<float> crop(size_t(w) * h * 3);
  for (int j = 0; j < h; ++j) {
    for (int i = 0; i < w * 3; ++i) {
      crop[size_t(j) * w * 3 + size_t(i)] =
          seen.rgb[(size_t(j + top) * kPanoW + size_t(left)) * 3 + size_t(i)];
    }
  }
  const std::string jpeg = Encode(crop, w, h, 3, "part.jpg", OIIO::TypeDesc::UINT8);
  absl::StatusOr<geometry::LinearImage> part = ingest::DecodeImage(jpeg, false, 1 << 24);
  ASSERT_TRUE(part.ok()) << part.status();
  ASSERT_NE(part->coding, nullptr);
  const ingest::CodecMap alone = ingest::DetectCodec(*part);
  ASSERT_TRUE(alone.jpeg);
  ASSERT_GT(alone.soft_pixels, 0) << "the test needs a JPEG whose coding left artefacts";
  geometry::LinearImage placed = *part;
  ASSERT_TRUE(
      ingest::PlaceInSphere(ingest::SphereWindow{kPanoW, kPanoH, left, top}, 1 << 24, placed)
          .ok());
  const ingest::CodecMap in_sphere = ingest::DetectCodec(placed);
  ASSERT_EQ(in_sphere.conf.pixels.size(), size_t(kPanoW) * kPanoH);
  size_t differ = 0, outside_not_one = 0;
  for (int j = 0; j < kPanoH; ++j) {
    for (int i = 0; i < kPanoW; ++i) {
      const float v = in_sphere.conf.pixels[size_t(j) * kPanoW + size_t(i)];
      if (i >= left && i < left + w && j >= top && j < top + h) {
        differ += v != alone.conf.pixels[size_t(j - top) * w + size_t(i - left)];
      } else {
        outside_not_one += v != 1.0f;
      }
    }
  }
  geometry::LinearImage misread = placed;
  misread.coded_window.reset();  // blocks from the placed image's corner
  const ingest::CodecMap misaligned = ingest::DetectCodec(misread);
  size_t moved = 0;
  for (int j = 0; j < h; ++j) {
    for (int i = 0; i < w; ++i) {
      moved += misaligned.conf.pixels[size_t(j + top) * kPanoW + size_t(i + left)] !=
               alone.conf.pixels[size_t(j) * w + size_t(i)];
    }
  }
  std::printf("codec map of a %dx%d JPEG part at (%d, %d): %lld soft pixels alone, %lld placed; "
              "%zu differ inside, %zu not 1 outside; read from the sphere's corner, %zu "
              "differ\n",
              w, h, left, top, (long long)alone.soft_pixels, (long long)in_sphere.soft_pixels,
              differ, outside_not_one, moved);
  EXPECT_EQ(differ, 0u);
  EXPECT_EQ(outside_not_one, 0u);
  EXPECT_EQ(in_sphere.soft_pixels, alone.soft_pixels);
  EXPECT_GT(moved, size_t(alone.soft_pixels) / 10);
}

// A cylindrical panorama (an E57 cylindricalRepresentation) is resampled into the part of the
// sphere it covers: its records agree with those of the equirect panorama of the same view
// where both see (up to the resampling of a textured scene), and the rows beyond the cylinder
// give none (invalidated). Taking the same image for an equirect part (its rows linear in
// elevation) puts the colours off by up to the cylinder's stretch, which the figures show.
TEST(AlphaMaskTest, ACylindricalPanoramaIsResampledIntoItsSphere) {
  const scenes::SyntheticRoom room = scenes::SyntheticRoom::Default();
  const geometry::Pose pose = scenes::CameraPoseForStation(room.Stations()[0]);
  const scenes::Panorama fine = scenes::RenderPanorama(room, pose, 4 * kPanoW, 4 * kPanoH, 2);
  const scenes::Panorama whole = scenes::RenderPanorama(room, pose, kPanoW, kPanoH, 2);
  // 360° in kPanoW columns; rows of square pixels at the horizon up to ±55° of elevation.
  const double pw = 2 * M_PI / kPanoW, radius = 2.0, ph = radius * pw;
  const int h = 2 * int(std::ceil(std::tan(55.0 * M_PI / 180) / pw));
  const double ppy = h / 2.0;
  const int FW = 4 * kPanoW, FH = 4 * kPanoH;
  std::vector<float> cyl(size_t(kPanoW) * h * 3);
  for (int v = 0; v < h; ++v) {
    const double psi = std::atan((ppy - (v + 0.5)) * ph / radius);
    for (int u = 0; u < kPanoW; ++u) {
      const double phi = 2 * M_PI * (0.5 - (u + 0.5) / kPanoW);
      // §2.1 in the fine panorama, read bilinearly between pixel centres.
      const double x = FW * (0.5 - phi / (2 * M_PI)) - 0.5, y = FH * (0.5 - psi / M_PI) - 0.5;
      const int x0 = int(std::floor(x)), y0 = std::clamp(int(std::floor(y)), 0, FH - 2);
      const double fx = x - x0, fy = std::clamp(y - y0, 0.0, 1.0);
      for (int c = 0; c < 3; ++c) {
        auto at = [&](int i, int j) {
          return fine.rgb[(size_t(j) * FW + size_t((i + FW) % FW)) * 3 + size_t(c)];
        };
        cyl[(size_t(v) * kPanoW + size_t(u)) * 3 + size_t(c)] =
            float((1 - fy) * ((1 - fx) * at(x0, y0) + fx * at(x0 + 1, y0)) +
                  fy * ((1 - fx) * at(x0, y0 + 1) + fx * at(x0 + 1, y0 + 1)));
      }
    }
  }
  const fs::path root = fs::temp_directory_path() / ("vasl-cyl-" + std::to_string(::getpid()));
  const std::string cylinder_png = Encode(cyl, kPanoW, h, 3, "cyl.png", OIIO::TypeDesc::UINT8);
  std::vector<float> whole_rgb(whole.rgb.begin(), whole.rgb.end());
  const RecordsByVossel truth =
      RgbRecords(root, room, Encode(whole_rgb, kPanoW, kPanoH, 3, "w.png", OIIO::TypeDesc::UINT8))
          .records;
  auto ingest_cylinder = [&](bool as_cylinder) {
    ingest::PanoramaData pano;
    pano.encoded_image = cylinder_png;
    if (as_cylinder) {
      pano.cylinder = ingest::CylinderImage{pw, ph, radius, ppy};
    } else {  // its rows taken as equirect ones, centred
      pano.sphere = ingest::SphereWindow{kPanoW, kPanoH, 0, (kPanoH - h) / 2};
    }
    return IngestCamera(root, room, pano, /*rebuild=*/true).records;
  };
  auto compare = [&](const RecordsByVossel& got, const char* what) {
    std::vector<float> diff;
    size_t invalid = 0;
    for (const auto& [key, r] : truth) {
      auto it = got.find(key);
      if (it == got.end()) continue;
      if (it->second.invalid) {
        ++invalid;
        continue;
      }
      if (r.invalid) continue;
      float d = 0.0f;
      for (int c = 0; c < 3; ++c) d = std::max(d, std::abs(it->second.v[c] - r.v[c]));
      diff.push_back(d);
    }
    std::sort(diff.begin(), diff.end());
    const float median = diff[diff.size() / 2], p95 = diff[diff.size() * 95 / 100];
    std::printf("%s: %zu records compared, |Δ| median %.4f, 95th percentile %.4f; %zu "
                "invalidated (beyond the cylinder)\n",
                what, diff.size(), median, p95, invalid);
    return std::make_tuple(median, p95, invalid);
  };
  const auto [median, p95, invalid] = compare(ingest_cylinder(true), "cylinder resampled");
  const float p95_linear =
      std::get<1>(compare(ingest_cylinder(false), "the same rows taken as equirect"));
  EXPECT_LT(median, 0.01f);
  EXPECT_LT(p95, 0.05f);
  EXPECT_GT(invalid, 1000u);  // the floor and ceiling beyond ±55°
  EXPECT_GT(p95_linear, 10 * p95);
}

}  // namespace
}  // namespace vasl

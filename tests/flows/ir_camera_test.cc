// Claims of an infrared camera's ingest (VASL-MODEL §2, §6: a record's value is linear
// radiometry): the same IR panorama sent as float (EXR), as 16-bit integer codes (a radiometric
// camera's PNG or TIFF: codes proportional to radiance) and as an 8-bit display image gives
// records on the same vossels; the 16-bit codes read linearly (code / 65535) to the float
// values within their quantisation, the 8-bit ones through the sRGB curve within half a code.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <map>
#include <string>
#include <tuple>
#include <vector>

#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include "lattice/engine.h"
#include "lattice/geometry/linear_image.h"
#include "lattice/store/project_store.h"
#include "tests/scenes/synthetic_scene.h"

namespace vasl {
namespace {
namespace fs = std::filesystem;

constexpr int kPanoW = 512;

// One channel of `values` (W×H, linear) encoded as `file_name`'s format in `type`: 16-bit codes
// round(v·65535), 8-bit codes through the sRGB curve, floats as they are.
std::string Encode(const std::vector<float>& values, int w, int h, const std::string& file_name,
                   OIIO::TypeDesc type) {
  std::vector<unsigned char> buffer;
  OIIO::Filesystem::IOVecOutput proxy(buffer);
  auto out = OIIO::ImageOutput::create(file_name, &proxy);
  EXPECT_TRUE(out != nullptr) << OIIO::geterror();
  if (!out) return {};
  OIIO::ImageSpec spec(w, h, 1, type);
  std::vector<unsigned char> pixels(values.size() * type.size());
  for (size_t p = 0; p < values.size(); ++p) {
    const float v = std::clamp(values[p], 0.0f, 1.0f);
    if (type == OIIO::TypeDesc::UINT16) {
      const uint16_t code = uint16_t(std::lround(v * 65535.0f));
      std::memcpy(&pixels[2 * p], &code, 2);
    } else if (type == OIIO::TypeDesc::UINT8) {
      pixels[p] = geometry::LinearToSrgb8(v);
    } else {
      std::memcpy(&pixels[4 * p], &values[p], 4);
    }
  }
  const bool ok = out->open(file_name, spec) && out->write_image(type, pixels.data()) &&
                  out->close();
  EXPECT_TRUE(ok) << out->geterror();
  return std::string(buffer.begin(), buffer.end());
}

// The IR records of a project holding station 0's LiDAR and `ir` as its IR panorama, by vossel.
std::map<std::tuple<int, int, int>, float> IrRecords(const fs::path& root,
                                                     const scenes::SyntheticRoom& room,
                                                     const std::string& ir) {
  std::map<std::tuple<int, int, int>, float> out;
  fs::remove_all(root);
  auto engine = Engine::Open(root);
  EXPECT_TRUE(engine.ok()) << engine.status();
  if (!engine.ok()) return out;
  store::ProjectSettings settings;
  settings.vossel_size_m = 0.05;
  EXPECT_TRUE((*engine)->CreateProject("p", settings).ok());
  auto scan = scenes::MakeScanInput(room, 0, scenes::LidarSettings::Small(1), 0);
  EXPECT_TRUE(scan.ok()) << scan.status();
  if (!scan.ok()) return out;
  ingest::PanoramaData pano;
  pano.name = "thermal";
  pano.modality = records::Modality::kIr;
  pano.pose = scenes::CameraPoseForStation(room.Stations()[0]);
  pano.encoded_image = ir;
  scan->panoramas.push_back(pano);
  auto r = (*engine)->IngestScan("p", *scan);
  EXPECT_TRUE(r.ok()) << r.status();
  if (!r.ok()) return out;
  auto st = store::ProjectStore::Open(root / "p");
  auto snap = (*st)->LoadSnapshot((*st)->head_version());
  EXPECT_TRUE(snap.ok()) << snap.status();
  const records::RecordSet& rec = (*snap)->records;
  for (size_t i = 0; i < rec.size(); ++i) {
    if (rec.modality[i] != int8_t(records::Modality::kIr)) continue;
    const openvdb::Coord c = (*snap)->geometry.coord[size_t(rec.vossel[i])];
    out[{c.x(), c.y(), c.z()}] = rec.value[records::kValueChannels * i];
  }
  fs::remove_all(root);
  return out;
}

TEST(IrCameraTest, IntegerCodesReadAsTheirEncodingSays) {
  const scenes::SyntheticRoom room = scenes::SyntheticRoom::Default();
  // The thermal panorama: the luminance of the room's albedo (linear, in [0.05, 0.95]).
  const scenes::Panorama seen = scenes::RenderPanorama(
      room, scenes::CameraPoseForStation(room.Stations()[0]), kPanoW, kPanoW / 2, 2);
  std::vector<float> radiance(size_t(kPanoW) * (kPanoW / 2));
  for (size_t p = 0; p < radiance.size(); ++p) {
    radiance[p] = scenes::Luminance(
        Eigen::Vector3f(seen.rgb[3 * p], seen.rgb[3 * p + 1], seen.rgb[3 * p + 2]));
  }
  const fs::path root = fs::temp_directory_path() / ("vasl-ir-" + std::to_string(::getpid()));
  const auto as_float = IrRecords(
      root, room, Encode(radiance, kPanoW, kPanoW / 2, "ir.exr", OIIO::TypeDesc::FLOAT));
  const auto as_16 = IrRecords(
      root, room, Encode(radiance, kPanoW, kPanoW / 2, "ir.png", OIIO::TypeDesc::UINT16));
  const auto as_8 = IrRecords(
      root, room, Encode(radiance, kPanoW, kPanoW / 2, "ir.png", OIIO::TypeDesc::UINT8));
  ASSERT_GT(as_float.size(), 10000u);
  auto compare = [&](const std::map<std::tuple<int, int, int>, float>& other, const char* what) {
    size_t missing = 0;
    double worst = 0.0, lo = 1.0, hi = 0.0;
    for (const auto& [key, v] : as_float) {
      auto it = other.find(key);
      if (it == other.end()) {
        ++missing;
        continue;
      }
      worst = std::max(worst, double(std::abs(it->second - v)));
      lo = std::min(lo, double(it->second));
      hi = std::max(hi, double(it->second));
    }
    std::printf("%s: %zu IR records (float: %zu), values %.3f-%.3f, %zu missing, max |Δ| %.3g\n",
                what, other.size(), as_float.size(), lo, hi, missing, worst);
    EXPECT_EQ(other.size(), as_float.size());
    EXPECT_EQ(missing, 0u);
    EXPECT_GE(lo, 0.04);  // linear radiometry of the albedo's luminance, not display codes
    EXPECT_LE(hi, 0.96);
    return worst;
  };
  // Records store a value as a half float (record_grid.cc), a step of 2⁻¹¹ below 1: 16-bit
  // codes, half a code (7.6e-6) from the float, land at most one such step away (where the
  // two fall on either side of a rounding boundary); read through the sRGB curve they were
  // 0.29 away.
  EXPECT_LE(compare(as_16, "16-bit PNG"), 0x1p-11);
  // 8-bit sRGB codes: half a code at the top of the curve, (1 - 0.991102) / 2, and a step.
  EXPECT_LE(compare(as_8, "8-bit PNG"), 0.0045 + 0x1p-11);
}

}  // namespace
}  // namespace vasl

// Decoding of panoramas (ingest): PNG, JPEG, EXR and TIFF through OpenImageIO, sRGB
// linearisation of integer encodings, clear errors for bytes that do not decode; and the real
// 8192×4096 panorama of ../shared/data, whose stated pixel pitch must equal §2.1's 2π/W.
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <regex>
#include <sstream>

#include <OpenImageIO/imageio.h>
#include <gtest/gtest.h>

#include "lattice/geometry/equirect.h"
#include "lattice/ingest/sources.h"

namespace vasl::ingest {
namespace {

std::filesystem::path DataDir() {
  const char* env = std::getenv("VASL_DATA_DIR");
  return env != nullptr ? std::filesystem::path(env) : std::filesystem::path("../shared/data");
}

std::string ReadFile(const std::filesystem::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

// Encodes a `channels`-channel gradient with OpenImageIO in the format the extension names.
std::string Encode(const std::string& ext, OIIO::TypeDesc type, int w, int h, int channels = 3) {
  const std::filesystem::path path =
      std::filesystem::temp_directory_path() / ("vasl-decode-" + std::to_string(::getpid()) + ext);
  std::vector<float> pixels(size_t(w) * h * channels);
  for (int j = 0; j < h; ++j)
    for (int i = 0; i < w; ++i)
      for (int c = 0; c < channels; ++c) {
        pixels[(size_t(j) * w + i) * channels + c] = float(i + c % 3) / float(w + 2);
      }
  auto out = OIIO::ImageOutput::create(path.string());
  OIIO::ImageSpec spec(w, h, channels, type);
  EXPECT_TRUE(out && out->open(path.string(), spec));
  EXPECT_TRUE(out->write_image(OIIO::TypeDesc::FLOAT, pixels.data()));
  out->close();
  std::string bytes = ReadFile(path);
  std::filesystem::remove(path);
  return bytes;
}

float SrgbToLinear(float c) { return c <= 0.04045f ? c / 12.92f : std::pow((c + 0.055f) / 1.055f, 2.4f); }

// Claim: every format the rig may send decodes; 8-bit encodings are taken as sRGB and
// linearised (within one 8-bit step), float EXR stays linear (exact).
TEST(ImageDecodeTest, DecodesEveryFormatAndLinearises) {
  const int w = 64, h = 32;
  for (const char* ext : {".png", ".jpg", ".tif"}) {
    auto image = DecodeImage(Encode(ext, OIIO::TypeDesc::UINT8, w, h), false, 1 << 20);
    ASSERT_TRUE(image.ok()) << ext << ": " << image.status();
    EXPECT_EQ(image->width_px, w);
    EXPECT_EQ(image->height_px, h);
    EXPECT_EQ(image->channels, 3);
    EXPECT_EQ(image->clip_value, 1.0f);
    for (int i = 0; i < w; i += 7) {
      const float encoded = float(i) / float(w + 2);
      // Half an 8-bit step of the encoding, carried through the sRGB curve (JPEG: lossy, 8 steps).
      const double steps = std::string(ext) == ".jpg" ? 8.0 : 0.5;
      const double tol = SrgbToLinear(std::min(1.0f, encoded + float(steps / 255.0))) - SrgbToLinear(encoded) + 1e-6;
      EXPECT_NEAR(image->pixels[(size_t(5) * w + i) * 3], SrgbToLinear(encoded), tol) << ext << " column " << i;
    }
  }
  auto exr = DecodeImage(Encode(".exr", OIIO::TypeDesc::FLOAT, w, h), false, 1 << 20);
  ASSERT_TRUE(exr.ok()) << exr.status();
  EXPECT_EQ(exr->clip_value, 0.0f);
  EXPECT_FLOAT_EQ(exr->pixels[(size_t(3) * w + 10) * 3 + 1], 11.0f / (w + 2));
  auto ir = DecodeImage(Encode(".png", OIIO::TypeDesc::UINT8, w, h), true, 1 << 20);
  ASSERT_TRUE(ir.ok());
  EXPECT_EQ(ir->channels, 1);
}

// Claim: bytes that are not an image, or a truncated image, are INVALID_ARGUMENT with a message
// naming the problem; an image above the pixel limit is RESOURCE_EXHAUSTED.
TEST(ImageDecodeTest, RejectsBadBytesAndLimits) {
  auto garbage = DecodeImage("definitely not an image", false, 1 << 20);
  EXPECT_EQ(garbage.status().code(), absl::StatusCode::kInvalidArgument);
  std::printf("garbage: %s\n", std::string(garbage.status().message()).c_str());
  std::string png = Encode(".png", OIIO::TypeDesc::UINT8, 64, 32);
  auto truncated = DecodeImage(png.substr(0, png.size() / 3), false, 1 << 20);
  EXPECT_EQ(truncated.status().code(), absl::StatusCode::kInvalidArgument);
  std::printf("truncated png: %s\n", std::string(truncated.status().message()).c_str());
  EXPECT_EQ(DecodeImage(png, false, 100).status().code(), absl::StatusCode::kResourceExhausted);
}

// Claim (§2.1, real data): the real panorama decodes at 8192×4096, and the pixel pitch its
// capture metadata states equals Δφ = 2π/W and Δψ = π/H to 1e-10 rad (the metadata differs
// from 2π/8192 by 2e-11 rad, a single-precision π).
TEST(ImageDecodeTest, RealPanoramaMatchesEquirectPitch) {
  const std::filesystem::path jpg = DataDir() / "panorama" / "image_atis_rcn_1.jpg";
  const std::filesystem::path meta = DataDir() / "panorama" / "image.json";
  if (!std::filesystem::exists(jpg) || !std::filesystem::exists(meta)) {
    GTEST_SKIP() << "real panorama not found under " << DataDir() << " (set VASL_DATA_DIR)";
  }
  auto image = DecodeImage(ReadFile(jpg), false, int64_t(16384) * 8192);
  ASSERT_TRUE(image.ok()) << image.status();
  EXPECT_EQ(image->width_px, 8192);
  EXPECT_EQ(image->height_px, 4096);
  double mean = 0.0;
  for (float v : image->pixels) mean += v;
  mean /= double(image->pixels.size());
  std::printf("real panorama %dx%d, mean linear value %.4f\n", image->width_px, image->height_px, mean);
  EXPECT_GT(mean, 0.0);
  EXPECT_LT(mean, 1.0);
  // The entry for image_atis_rcn_1 in image.json.
  const std::string json = ReadFile(meta);
  const size_t at = json.find("\"image_atis_rcn_1\"");
  ASSERT_NE(at, std::string::npos);
  std::smatch m;
  const std::string entry = json.substr(at, 600);
  ASSERT_TRUE(std::regex_search(entry, m, std::regex("\"pixelWidth\"\\s*:\\s*([0-9.eE+-]+)")));
  const double pixel_width = std::stod(m[1]);
  ASSERT_TRUE(std::regex_search(entry, m, std::regex("\"pixelHeight\"\\s*:\\s*([0-9.eE+-]+)")));
  const double pixel_height = std::stod(m[1]);
  const geometry::EquirectSize size{image->width_px, image->height_px};
  std::printf("stated pixel pitch %.17g rad, 2π/W = %.17g rad\n", pixel_width, geometry::AzimuthPitchRad(size));
  EXPECT_NEAR(pixel_width, geometry::AzimuthPitchRad(size), 1e-10);
  EXPECT_NEAR(pixel_height, geometry::ElevationPitchRad(size), 1e-10);
}

// Claim (issue "Reliability"): a small image that declares many channels cannot make the
// decoder size a huge buffer: more than 16 channels is RESOURCE_EXHAUSTED, naming the count.
TEST(ImageDecodeTest, RefusesImagesWithTooManyChannels) {
  auto many = DecodeImage(Encode(".exr", OIIO::TypeDesc::HALF, 8, 4, 40), false, 1 << 20);
  ASSERT_FALSE(many.ok());
  EXPECT_EQ(many.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(many.status().message().find("40 channels"), std::string::npos) << many.status();
  auto four = DecodeImage(Encode(".exr", OIIO::TypeDesc::HALF, 8, 4, 4), false, 1 << 20);
  EXPECT_TRUE(four.ok()) << four.status();
}

}  // namespace
}  // namespace vasl::ingest

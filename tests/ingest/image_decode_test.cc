// Decoding of panoramas (ingest): PNG, JPEG, EXR and TIFF through OpenImageIO, sRGB
// linearisation of integer encodings, clear errors for bytes that do not decode; and the real
// 8192×4096 panorama of ../shared/data, whose stated pixel pitch must equal §2.1's 2π/W.
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <regex>
#include <sstream>

#include <OpenImageIO/imageio.h>
#include <gtest/gtest.h>

#include "lattice/geometry/equirect.h"
#include "lattice/ingest/image_memory.h"
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

int32_t ReadInt32At(const std::string& bytes, size_t at) {
  int32_t v;
  std::memcpy(&v, bytes.data() + at, 4);
  return v;
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
// Claim (ARCHITECTURE "Errors": bad input is refused, never read beyond): the in-memory reader
// OpenImageIO decodes through reads only within the bytes sent. OpenImageIO 2.4's own reader
// copied from beyond them when a read started at or past their end (fuzz_backproject_image's
// third find: an EXR whose offset table points there); such a file is now refused, and a read
// past the end copies nothing.
TEST(ImageDecodeTest, ReadsNothingBeyondTheBytesSent) {
  const std::string bytes = "0123456789";
  internal::BoundedMemReader reader(bytes.data(), bytes.size());
  char out[16];
  std::memset(out, '#', sizeof out);
  EXPECT_EQ(reader.pread(out, 5, 8), 2u);  // the last two bytes, then the end
  EXPECT_EQ(std::string(out, 3), "89#");
  for (int64_t offset : {int64_t{10}, int64_t{11}, int64_t{1} << 40, int64_t{-1}}) {
    std::memset(out, '#', sizeof out);
    EXPECT_EQ(reader.pread(out, 4, offset), 0u) << "offset " << offset;
    EXPECT_EQ(std::string(out, 4), "####") << "offset " << offset;
  }
  ASSERT_TRUE(reader.seek(7));
  EXPECT_EQ(reader.read(out, 8), 3u);
  EXPECT_EQ(reader.tell(), 10);
  EXPECT_EQ(reader.read(out, 8), 0u);

  // An EXR whose every chunk offset points past its end.
  const std::string exr = Encode(".exr", OIIO::TypeDesc::FLOAT, 64, 32);
  size_t table = 8;  // after the magic number and version: attributes up to an empty name
  while (table < exr.size() && exr[table] != '\0') {
    const size_t type = exr.find('\0', table) + 1;
    const size_t size_at = exr.find('\0', type) + 1;
    table = size_at + 4 + size_t(ReadInt32At(exr, size_at));
  }
  ++table;  // the offset table follows the empty name
  ASSERT_LT(table, exr.size());
  std::string past = exr;
  const uint64_t first = uint64_t(exr.size()) + 4096;
  int chunks = 0;
  for (size_t at = table; at + 8 <= past.size(); at += 8, ++chunks) {
    uint64_t offset;
    std::memcpy(&offset, &exr[at], 8);
    if (offset <= table || offset >= exr.size()) break;  // past the table
    const uint64_t moved = first + 8 * uint64_t(chunks);
    std::memcpy(&past[at], &moved, 8);
  }
  ASSERT_GT(chunks, 0);
  auto refused = DecodeImage(past, false, 1 << 20);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument) << refused.status();
  std::printf("EXR with %d chunk offsets past its end: %s\n", chunks,
              std::string(refused.status().message()).c_str());
}

TEST(ImageDecodeTest, RefusesImagesWithTooManyChannels) {
  auto many = DecodeImage(Encode(".exr", OIIO::TypeDesc::HALF, 8, 4, 40), false, 1 << 20);
  ASSERT_FALSE(many.ok());
  EXPECT_EQ(many.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(many.status().message().find("40 channels"), std::string::npos) << many.status();
  auto four = DecodeImage(Encode(".exr", OIIO::TypeDesc::HALF, 8, 4, 4), false, 1 << 20);
  EXPECT_TRUE(four.ok()) << four.status();
}

// Claim (issue "Reliability"): an EXR header cannot make OpenEXR allocate more than the bytes
// sent. The fuzzer's 16-byte reproducer (an opaque attribute claiming 2 GiB) is refused before
// OpenEXR reads it, as is a data window beyond the pixel limit; every truncation of a real
// header is an error, never a crash; real single- and multi-part files pass the walk unchanged.
TEST(ImageDecodeTest, ExrHeadersAreWalkedBeforeOpenExrAllocates) {
  const std::string oom("v/1\x01\x02\0\0\0a\0x\0\xf0\xff\xff\x7f", 16);
  auto refused = DecodeImage(oom, false, 1 << 20);
  ASSERT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument) << refused.status();
  EXPECT_NE(refused.status().message().find("claims 2147483632 bytes"), std::string::npos)
      << refused.status();
  std::printf("2 GiB attribute: %s\n", std::string(refused.status().message()).c_str());

  const std::string exr = Encode(".exr", OIIO::TypeDesc::HALF, 64, 32);
  ASSERT_TRUE(internal::CheckExrHeaders(exr, 1 << 20).ok());
  // The data window is a box2i after the name "dataWindow" and type "box2i" and size 16.
  const std::string key("dataWindow\0box2i\0", 17);
  const size_t window = exr.find(key);
  ASSERT_NE(window, std::string::npos);
  std::string huge = exr;
  const int32_t big = 1 << 30;
  std::memcpy(&huge[window + key.size() + 4 + 8], &big, 4);  // xMax
  auto too_big = DecodeImage(huge, false, 1 << 20);
  EXPECT_EQ(too_big.status().code(), absl::StatusCode::kResourceExhausted) << too_big.status();
  std::string inverted = exr;
  const int32_t negative = -5;
  std::memcpy(&inverted[window + key.size() + 4 + 8], &negative, 4);
  EXPECT_EQ(DecodeImage(inverted, false, 1 << 20).status().code(), absl::StatusCode::kInvalidArgument);

  // Every cut inside the header (up to the end of its attribute list) is refused cleanly.
  const size_t header_end = exr.find(std::string("\0", 1), window + key.size() + 4 + 16);
  int refused_cuts = 0;
  for (size_t cut = 0; cut < std::min(header_end, exr.size()); ++cut) {
    auto part = DecodeImage(exr.substr(0, cut), false, 1 << 20);
    EXPECT_FALSE(part.ok()) << "cut at " << cut;
    refused_cuts += !part.ok();
  }
  std::printf("header cuts refused: %d of %zu\n", refused_cuts, std::min(header_end, exr.size()));

  // A channel list whose size disagrees with its entries would put OpenEXR out of step with the
  // bytes (it reads entries up to an empty name): refused, as the fuzzer's second find showed.
  const std::string chlist("channels\0chlist\0", 16);
  const size_t channels = exr.find(chlist);
  ASSERT_NE(channels, std::string::npos);
  std::string desynced = exr;
  const int32_t declared = ReadInt32At(exr, channels + chlist.size()) + 16;
  std::memcpy(&desynced[channels + chlist.size()], &declared, 4);
  auto out_of_step = DecodeImage(desynced, false, 1 << 20);
  EXPECT_EQ(out_of_step.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(out_of_step.status().message().find("does not fill exactly"), std::string::npos)
      << out_of_step.status();

  // A tiled file with MIP levels passes the walk (its offset table counts every level's tiles).
  const std::filesystem::path tiled_path = std::filesystem::temp_directory_path() /
                                           ("vasl-tiled-" + std::to_string(::getpid()) + ".exr");
  {
    auto out = OIIO::ImageOutput::create(tiled_path.string());
    OIIO::ImageSpec spec(37, 19, 3, OIIO::TypeDesc::HALF);
    spec.tile_width = spec.tile_height = 8;
    spec.attribute("textureformat", "Plain Texture");  // OpenImageIO then writes MIP levels
    ASSERT_TRUE(out && out->open(tiled_path.string(), spec, OIIO::ImageOutput::Create));
    std::vector<float> level(37 * 19 * 3, 0.5f);
    ASSERT_TRUE(out->write_image(OIIO::TypeDesc::FLOAT, level.data()));
    for (int w = 18, h = 9; w >= 1 && h >= 1; w /= 2, h /= 2) {
      OIIO::ImageSpec mip(w, h, 3, OIIO::TypeDesc::HALF);
      mip.tile_width = mip.tile_height = 8;
      ASSERT_TRUE(out->open(tiled_path.string(), mip, OIIO::ImageOutput::AppendMIPLevel))
          << out->geterror();
      ASSERT_TRUE(out->write_image(OIIO::TypeDesc::FLOAT, level.data()));
    }
    out->close();
  }
  const std::string tiled = ReadFile(tiled_path);
  std::filesystem::remove(tiled_path);
  EXPECT_TRUE(internal::CheckExrHeaders(tiled, 1 << 20).ok())
      << internal::CheckExrHeaders(tiled, 1 << 20);
  auto tiled_image = DecodeImage(tiled, false, 1 << 20);
  ASSERT_TRUE(tiled_image.ok()) << tiled_image.status();
  EXPECT_EQ(tiled_image->width_px, 37);
  // Cut after its headers, its offsets no longer fit: refused before OpenEXR sizes the table.
  // 37×19 in 8×8 tiles with MIP levels rounded down has 15 + 6 + 2 + 1 + 1 + 1 = 26 tiles.
  std::string first_offset_fault;
  for (size_t cut = 0; cut < tiled.size() && first_offset_fault.empty(); ++cut) {
    const absl::Status s = internal::CheckExrHeaders(tiled.substr(0, cut), 1 << 20);
    EXPECT_FALSE(s.ok()) << "cut at " << cut;
    if (s.message().find("chunks") != std::string::npos) first_offset_fault = std::string(s.message());
  }
  EXPECT_NE(first_offset_fault.find("imply 26 chunks"), std::string::npos) << first_offset_fault;

  // A two-part file (two subimages) passes the walk and its first part decodes.
  const std::filesystem::path path = std::filesystem::temp_directory_path() /
                                     ("vasl-multipart-" + std::to_string(::getpid()) + ".exr");
  {
    auto out = OIIO::ImageOutput::create(path.string());
    ASSERT_TRUE(out && out->supports("multiimage"));
    OIIO::ImageSpec specs[2] = {OIIO::ImageSpec(16, 8, 3, OIIO::TypeDesc::HALF),
                                OIIO::ImageSpec(16, 8, 1, OIIO::TypeDesc::FLOAT)};
    specs[0].attribute("name", "colour");
    specs[1].attribute("name", "weight");
    ASSERT_TRUE(out->open(path.string(), 2, specs)) << out->geterror();
    std::vector<float> a(16 * 8 * 3, 0.25f), b(16 * 8, 2.0f);
    ASSERT_TRUE(out->write_image(OIIO::TypeDesc::FLOAT, a.data()));
    ASSERT_TRUE(out->open(path.string(), specs[1], OIIO::ImageOutput::AppendSubimage));
    ASSERT_TRUE(out->write_image(OIIO::TypeDesc::FLOAT, b.data()));
    out->close();
  }
  const std::string multipart = ReadFile(path);
  std::filesystem::remove(path);
  EXPECT_TRUE(internal::CheckExrHeaders(multipart, 1 << 20).ok());
  auto first = DecodeImage(multipart, false, 1 << 20);
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_EQ(first->width_px, 16);
  EXPECT_FLOAT_EQ(first->pixels[5], 0.25f);
}

}  // namespace
}  // namespace vasl::ingest

// VASL-MODEL §8 outputs: the multi-channel EXR (OpenEXR: half floats, float depth) and the 8-bit
// sRGB PNG (OIIO).
#include "lattice/render/encode.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <limits>
#include <map>
#include <random>
#include <string>
#include <vector>

#include <Imath/half.h>
#include <OpenEXR/ImfChannelList.h>
#include <OpenEXR/ImfFrameBuffer.h>
#include <OpenEXR/ImfHeader.h>
#include <OpenEXR/ImfIO.h>
#include <OpenEXR/ImfDeepFrameBuffer.h>
#include <OpenEXR/ImfDeepScanLineInputFile.h>
#include <OpenEXR/ImfInputFile.h>
#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>
#include <gtest/gtest.h>

#include "lattice/memory/isa.h"

namespace vasl::render {
namespace {

/// An Imf::IStream over bytes held in memory.
class StringIStream : public Imf::IStream {
 public:
  explicit StringIStream(const std::string& bytes) : Imf::IStream("memory.exr"), bytes_(bytes) {}
  bool read(char c[], int n) override {
    if (pos_ + n > bytes_.size()) throw std::runtime_error("read past the end of the EXR");
    std::memcpy(c, bytes_.data() + pos_, n);
    pos_ += n;
    return pos_ < bytes_.size();
  }
  uint64_t tellg() override { return pos_; }
  void seekg(uint64_t pos) override { pos_ = pos; }

 private:
  const std::string& bytes_;
  size_t pos_ = 0;
};

/// A 7×5 image with distinct values in every channel, some no-hit pixels (Z = +inf).
RenderImage MakeImage() {
  RenderImage img;
  img.width_px = 7;
  img.height_px = 5;
  const size_t n = 35;
  img.rgb.resize(3 * n);
  img.depth_m.resize(n);
  img.normal.resize(3 * n);
  img.uncertainty.resize(n);
  for (size_t p = 0; p < n; ++p) {
    for (int c = 0; c < 3; ++c) {
      img.rgb[3 * p + c] = 0.01f * p + 0.1f * c + 1e-7f;
      img.normal[3 * p + c] = std::sin(0.37f * p + c);
    }
    img.depth_m[p] = p % 6 == 0 ? std::numeric_limits<float>::infinity() : 1.5f + 0.123f * p;
    img.uncertainty[p] = 1.0f / (p + 3);
  }
  return img;
}

// Claim (§8 outputs, encode.h): the EXR holds exactly the channels R, G, B, N.x, N.y, N.z, U, A
// as HALF and Z as FLOAT over a W×H data window, RLE-compressed (lossless), row 0 = top; Z reads
// back bit-exact (+inf for no-hit pixels) and every other value as its nearest half, bit-exact
// (Imath::half's rounding, to nearest even).
TEST(EncodeTest, ExrRoundTripKeepsHalvesAndFloatDepth) {
  const RenderImage img = MakeImage();
  auto bytes = EncodeExr(img);
  ASSERT_TRUE(bytes.ok()) << bytes.status();
  StringIStream stream(*bytes);
  Imf::InputFile file(stream);
  const Imf::Header& header = file.header();
  EXPECT_EQ(header.compression(), Imf::RLE_COMPRESSION);
  EXPECT_EQ(header.lineOrder(), Imf::INCREASING_Y);
  const Imath::Box2i dw = header.dataWindow();
  EXPECT_EQ(dw.min.x, 0);
  EXPECT_EQ(dw.min.y, 0);
  EXPECT_EQ(dw.max.x, img.width_px - 1);
  EXPECT_EQ(dw.max.y, img.height_px - 1);
  std::vector<std::string> names;
  for (auto it = header.channels().begin(); it != header.channels().end(); ++it) {
    names.push_back(it.name());
    EXPECT_EQ(it.channel().type, it.name() == std::string("Z") ? Imf::FLOAT : Imf::HALF)
        << it.name();
  }
  // OpenEXR lists channels sorted by name.
  EXPECT_EQ(names, (std::vector<std::string>{"A", "B", "G", "N.x", "N.y", "N.z", "R", "U", "Z"}));

  const size_t n = static_cast<size_t>(img.width_px) * img.height_px;
  std::map<std::string, std::vector<float>> planes;
  Imf::FrameBuffer frame;
  for (const std::string& name : names) {
    planes[name].assign(n, -1.0f);
    frame.insert(name, Imf::Slice(Imf::FLOAT, reinterpret_cast<char*>(planes[name].data()),
                                  sizeof(float), sizeof(float) * img.width_px));
  }
  file.setFrameBuffer(frame);
  file.readPixels(dw.min.y, dw.max.y);
  int64_t mismatches = 0;
  double worst_relative = 0.0, worst_small = 0.0;  // of the half channels, against the floats
  auto same = [&](float a, float b) { mismatches += std::memcmp(&a, &b, sizeof(float)) != 0; };
  auto half = [&](float read, float value) {
    same(read, float(Imath::half(value)));
    // Relative to the value within half's normal range (from 2^-14); below it, subnormal
    // halves keep an absolute step of 2^-24 (half of it at worst).
    if (std::abs(value) >= std::ldexp(1.0f, -14)) {
      worst_relative = std::max(worst_relative, double(std::abs(read - value) / std::abs(value)));
    } else {
      worst_small = std::max(worst_small, double(std::abs(read - value)));
    }
  };
  for (size_t p = 0; p < n; ++p) {
    half(planes["R"][p], img.rgb[3 * p + 0]);
    half(planes["G"][p], img.rgb[3 * p + 1]);
    half(planes["B"][p], img.rgb[3 * p + 2]);
    same(planes["Z"][p], img.depth_m[p]);
    half(planes["N.x"][p], img.normal[3 * p + 0]);
    half(planes["N.y"][p], img.normal[3 * p + 1]);
    half(planes["N.z"][p], img.normal[3 * p + 2]);
    half(planes["U"][p], img.uncertainty[p]);
    // An image without an alpha array (made before it existed) covers its hit pixels.
    same(planes["A"][p], std::isfinite(img.depth_m[p]) ? 1.0f : 0.0f);
  }
  std::printf("EXR half channels: worst relative error %.2e (half's bound 2^-11 = %.2e), "
              "below 2^-14 worst absolute %.2e (bound 2^-25 = %.2e)\n",
              worst_relative, std::ldexp(1.0, -11), worst_small, std::ldexp(1.0, -25));
  EXPECT_LE(worst_relative, std::ldexp(1.0, -11));
  EXPECT_LE(worst_small, std::ldexp(1.0, -25));
  std::printf("EXR %dx%d: %zu bytes, %zu channels, %lld of %zu values differ (bitwise)\n",
              img.width_px, img.height_px, bytes->size(), names.size(), (long long)mismatches,
              9 * n);
  EXPECT_EQ(mismatches, 0);
  EXPECT_TRUE(std::isinf(planes["Z"][0]));
  // Row 1 is the second row.
  EXPECT_EQ(planes["R"][img.width_px], float(Imath::half(img.rgb[3 * img.width_px])));
}

// Claim (encode.cc ToHalves): the EXR's halves are the same bits whichever instruction set
// converts them (F16C eight at a time, or Imath::half one by one): the same file under every
// cap, over values that span half's range (subnormals, overflow to infinity, negatives, zeros).
TEST(EncodeTest, HalfChannelsAreTheSameBitsOnEveryIsa) {
  RenderImage img;
  img.width_px = 61;  // not a multiple of 8: each band's tail goes the scalar way
  img.height_px = 37;
  const size_t n = size_t(img.width_px) * size_t(img.height_px);
  std::mt19937 rng(5);
  std::uniform_real_distribution<float> exponent(-27.0f, 17.0f), unit(-1.0f, 1.0f);
  auto value = [&] { return std::copysign(std::exp2(exponent(rng)), unit(rng)); };
  img.rgb.resize(3 * n);
  img.normal.resize(3 * n);
  img.depth_m.resize(n);
  img.uncertainty.resize(n);
  img.alpha.resize(n);
  for (size_t i = 0; i < 3 * n; ++i) {
    img.rgb[i] = value();
    img.normal[i] = unit(rng);
  }
  for (size_t p = 0; p < n; ++p) {
    img.depth_m[p] = p % 9 == 0 ? std::numeric_limits<float>::infinity() : 0.5f + std::abs(value());
    img.uncertainty[p] = p % 7 == 0 ? std::numeric_limits<float>::infinity() : std::abs(value());
    img.alpha[p] = p % 5 == 0 ? 0.0f : (p % 3 == 0 ? -0.0f : 1.0f);
  }
  img.rgb[0] = 65504.0f;   // half's largest
  img.rgb[1] = 65520.0f;   // rounds to +inf
  img.rgb[2] = 5.96e-8f;   // half's least subnormal
  img.rgb[3] = 2.98e-8f;   // half of it: to zero (ties to even)
  std::map<memory::Isa, std::string> files;
  for (memory::Isa isa : {memory::Isa::kBaseline, memory::Isa::kAvx2, memory::Isa::kX86_64_V4}) {
    if (!memory::Supports(isa)) continue;
    memory::SetIsaCap(isa);
    auto bytes = EncodeExr(img);
    memory::SetIsaCap(memory::Isa::kX86_64_V4);
    ASSERT_TRUE(bytes.ok()) << bytes.status();
    files[isa] = *bytes;
  }
  std::printf("EXR under %zu instruction sets: %zu bytes each\n", files.size(),
              files.begin()->second.size());
  for (const auto& [isa, bytes] : files) {
    EXPECT_EQ(bytes, files.begin()->second) << "cap " << int(isa);
  }
}

/// The sRGB OETF written out independently in double precision, then quantised to 8 bits.
int ExpectedSrgb8(double linear) {
  if (!(linear > 0.0)) return 0;
  if (linear >= 1.0) return 255;
  const double e = linear <= 0.0031308 ? 12.92 * linear : 1.055 * std::pow(linear, 1 / 2.4) - 0.055;
  return static_cast<int>(std::lround(e * 255.0));
}

// Claim (§8 outputs): the PNG is 8-bit RGB with the sRGB transfer of the linear colour, clamped
// to [0, 1]: anchors 0.18 → 118, 0.5 → 188, 1 → 255, −0.2 → 0, 1.7 → 255, NaN → 0; a 256-step
// ramp decodes (OIIO) to the expected values within ±1.
TEST(EncodeTest, PngIsEightBitSrgb) {
  RenderImage img;
  img.width_px = 256;
  img.height_px = 2;
  const size_t n = 512;
  img.rgb.resize(3 * n);
  img.depth_m.assign(n, 1.0f);
  img.normal.assign(3 * n, 0.0f);
  img.uncertainty.assign(n, 0.0f);
  for (int i = 0; i < 256; ++i) {  // row 0: ramp in R, reversed in G, squared in B
    const float x = i / 255.0f;
    img.rgb[3 * i + 0] = x;
    img.rgb[3 * i + 1] = 1.0f - x;
    img.rgb[3 * i + 2] = x * x;
  }
  const float anchors[] = {0.18f, 0.5f, 1.0f, -0.2f, 1.7f, std::nanf(""), 0.0031308f, 0.001f};
  const int anchor_expect[] = {118, 188, 255, 0, 255, 0, 10, 3};
  for (int a = 0; a < 8; ++a) {
    for (int c = 0; c < 3; ++c) img.rgb[3 * (256 + a) + c] = anchors[a];
  }
  auto bytes = EncodePng(img);
  ASSERT_TRUE(bytes.ok()) << bytes.status();
  ASSERT_GE(bytes->size(), 8u);
  EXPECT_EQ(bytes->substr(1, 3), "PNG");

  std::vector<unsigned char> buffer(bytes->begin(), bytes->end());
  OIIO::Filesystem::IOMemReader reader(buffer.data(), buffer.size());
  auto in = OIIO::ImageInput::open("render.png", nullptr, &reader);
  ASSERT_TRUE(in) << OIIO::geterror();
  const OIIO::ImageSpec& spec = in->spec();
  EXPECT_EQ(spec.width, 256);
  EXPECT_EQ(spec.height, 2);
  EXPECT_EQ(spec.nchannels, 4);
  EXPECT_EQ(spec.alpha_channel, 3);
  EXPECT_EQ(spec.format, OIIO::TypeDesc::UINT8);
  std::vector<uint8_t> px(4 * n);
  ASSERT_TRUE(in->read_image(0, 0, 0, 4, OIIO::TypeDesc::UINT8, px.data())) << in->geterror();
  in->close();

  int worst = 0;
  for (int i = 0; i < 256; ++i) {
    for (int c = 0; c < 3; ++c) {
      worst = std::max(worst, std::abs(px[4 * i + c] - ExpectedSrgb8(img.rgb[3 * i + c])));
    }
  }
  int anchor_worst = 0;
  for (int a = 0; a < 8; ++a) {
    for (int c = 0; c < 3; ++c) {
      anchor_worst = std::max(anchor_worst, std::abs(px[4 * (256 + a) + c] - anchor_expect[a]));
    }
  }
  std::printf("PNG 256x2: %zu bytes; ramp worst |decoded − expected| = %d; anchors 0.18→%d "
              "0.5→%d 1→%d −0.2→%d 1.7→%d NaN→%d, worst anchor error %d\n",
              bytes->size(), worst, px[4 * 256], px[4 * 257], px[4 * 258], px[4 * 259],
              px[4 * 260], px[4 * 261], anchor_worst);
  EXPECT_LE(worst, 1);
  EXPECT_LE(anchor_worst, 1);
  int opaque = 0;
  for (size_t p = 0; p < n; ++p) opaque += px[4 * p + 3] == 255;
  EXPECT_EQ(opaque, int(n)) << "every pixel hit (an image without alpha counts hits as covered)";
}

// Claim (§8: no colour is not black): a hit pixel without colour (alpha 0) is neutral grey with
// alpha 0 in the PNG; a pixel that hit nothing is black with alpha 0; the EXR's A channel
// carries the coverage and U = +inf stays.
TEST(EncodeTest, NoColourIsNotBlack) {
  RenderImage img = MakeImage();
  const size_t n = img.depth_m.size();
  img.alpha.assign(n, 1.0f);
  for (size_t p = 0; p < n; ++p) {
    if (!std::isfinite(img.depth_m[p])) img.alpha[p] = 0.0f;
    if (p % 5 == 1) {  // hit, but the vossel has no colour
      img.alpha[p] = 0.0f;
      img.uncertainty[p] = std::numeric_limits<float>::infinity();
      for (int c = 0; c < 3; ++c) img.rgb[3 * p + c] = 0.0f;
    }
  }
  auto png = EncodePng(img);
  ASSERT_TRUE(png.ok()) << png.status();
  std::vector<unsigned char> buffer(png->begin(), png->end());
  OIIO::Filesystem::IOMemReader reader(buffer.data(), buffer.size());
  OIIO::ImageSpec config;  // read the file's own RGB, not premultiplied by alpha
  config.attribute("oiio:UnassociatedAlpha", 1);
  OIIO::Filesystem::IOProxy* proxy = &reader;
  config.attribute("oiio:ioproxy", OIIO::TypeDesc::PTR, &proxy);
  auto in = OIIO::ImageInput::open("render.png", &config);
  ASSERT_TRUE(in);
  std::vector<uint8_t> px(4 * n);
  ASSERT_TRUE(in->read_image(0, 0, 0, 4, OIIO::TypeDesc::UINT8, px.data()));
  in->close();
  int colourless = 0, missed = 0;
  for (size_t p = 0; p < n; ++p) {
    const bool hit = std::isfinite(img.depth_m[p]);
    if (hit && img.alpha[p] == 0.0f) {
      ++colourless;
      EXPECT_EQ(px[4 * p], 128);
      EXPECT_EQ(px[4 * p + 3], 0);
    } else if (!hit) {
      ++missed;
      EXPECT_EQ(px[4 * p], 0);
      EXPECT_EQ(px[4 * p + 3], 0);
    } else {
      EXPECT_EQ(px[4 * p + 3], 255);
    }
  }
  EXPECT_GT(colourless, 3);
  EXPECT_GT(missed, 3);
  auto exr = EncodeExr(img);
  ASSERT_TRUE(exr.ok());
  StringIStream stream(*exr);
  Imf::InputFile file(stream);
  std::vector<float> a(n, -1.0f), u(n, -1.0f);
  Imf::FrameBuffer frame;
  frame.insert("A", Imf::Slice(Imf::FLOAT, reinterpret_cast<char*>(a.data()), sizeof(float),
                               sizeof(float) * img.width_px));
  frame.insert("U", Imf::Slice(Imf::FLOAT, reinterpret_cast<char*>(u.data()), sizeof(float),
                               sizeof(float) * img.width_px));
  file.setFrameBuffer(frame);
  file.readPixels(0, img.height_px - 1);
  EXPECT_EQ(a, img.alpha);
  for (size_t p = 0; p < n; ++p) {
    if (p % 5 == 1) EXPECT_TRUE(std::isinf(u[p]));
  }
}

// Claim (ARCHITECTURE "Errors"): an image whose arrays disagree with its size is
// INVALID_ARGUMENT for both encoders.
TEST(EncodeTest, RejectsInconsistentImage) {
  RenderImage img = MakeImage();
  img.uncertainty.pop_back();
  EXPECT_EQ(EncodeExr(img).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(EncodePng(img).status().code(), absl::StatusCode::kInvalidArgument);
  RenderImage empty;
  EXPECT_EQ(EncodeExr(empty).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(EncodePng(empty).status().code(), absl::StatusCode::kInvalidArgument);
}

// Claim (§8 outputs): the deep EXR holds each pixel's layers as samples front to back with
// float R, G, B, A, Z, and reads back bit for bit (OpenEXR's deep scanline reader).
TEST(EncodeTest, DeepExrRoundTrip) {
  RenderImage img = MakeImage();
  const size_t n = img.depth_m.size(), L = 3;
  img.layers = int(L);
  img.layer_count.assign(n, 0);
  img.deep_depth_m.assign(n * L, std::numeric_limits<float>::infinity());
  img.deep_rgb.assign(3 * n * L, 0.0f);
  img.deep_alpha.assign(n * L, 0.0f);
  size_t samples = 0;
  for (size_t p = 0; p < n; ++p) {
    img.layer_count[p] = uint8_t(p % 4 == 3 ? 0 : 1 + p % 3);
    for (size_t l = 0; l < img.layer_count[p]; ++l, ++samples) {
      img.deep_depth_m[p * L + l] = 1.0f + float(l) + 0.01f * float(p);
      img.deep_alpha[p * L + l] = (p + l) % 2 ? 1.0f : 0.0f;
      for (int c = 0; c < 3; ++c) img.deep_rgb[3 * (p * L + l) + c] = 0.1f * float(c + l) + 0.001f * p;
    }
  }
  auto bytes = EncodeDeepExr(img);
  ASSERT_TRUE(bytes.ok()) << bytes.status();
  StringIStream stream(*bytes);
  Imf::DeepScanLineInputFile file(stream);
  const int w = img.width_px, h = img.height_px;
  // One frame buffer: the counts first, then the per-pixel sample pointers filled in.
  std::vector<unsigned int> count(n);
  std::vector<std::vector<float>> z(n), a(n), r(n);
  std::vector<float*> zp(n), ap(n), rp(n);
  Imf::DeepFrameBuffer frame;
  frame.insertSampleCountSlice(Imf::Slice(Imf::UINT, reinterpret_cast<char*>(count.data()),
                                          sizeof(unsigned int), sizeof(unsigned int) * w));
  for (const auto& [name, ptr] : {std::pair<const char*, std::vector<float*>*>{"Z", &zp}, {"A", &ap}, {"R", &rp}}) {
    frame.insert(name, Imf::DeepSlice(Imf::FLOAT, reinterpret_cast<char*>(ptr->data()),
                                      sizeof(float*), sizeof(float*) * w, sizeof(float)));
  }
  file.setFrameBuffer(frame);
  file.readPixelSampleCounts(0, h - 1);
  for (size_t p = 0; p < n; ++p) {
    ASSERT_EQ(count[p], img.layer_count[p]) << p;
    z[p].resize(count[p]);
    a[p].resize(count[p]);
    r[p].resize(count[p]);
    zp[p] = z[p].data();
    ap[p] = a[p].data();
    rp[p] = r[p].data();
  }
  file.readPixels(0, h - 1);
  size_t same = 0;
  for (size_t p = 0; p < n; ++p) {
    for (size_t l = 0; l < count[p]; ++l) {
      same += z[p][l] == img.deep_depth_m[p * L + l] && a[p][l] == img.deep_alpha[p * L + l] &&
              r[p][l] == img.deep_rgb[3 * (p * L + l)];
    }
  }
  std::printf("deep EXR: %zu samples over %zu pixels, %zu bytes, %zu read back exactly\n",
              samples, n, bytes->size(), same);
  EXPECT_EQ(same, samples);
}

/// A W×H image with varied values in every channel and layer, hits and misses.
RenderImage MakeLargeImage(int w, int h, int layers) {
  RenderImage img;
  img.width_px = w;
  img.height_px = h;
  const size_t n = size_t(w) * size_t(h), L = size_t(layers);
  img.rgb.resize(3 * n);
  img.depth_m.resize(n);
  img.normal.resize(3 * n);
  img.uncertainty.resize(n);
  img.alpha.resize(n);
  img.layers = layers;
  img.layer_count.assign(n, 0);
  img.deep_depth_m.assign(n * L, std::numeric_limits<float>::infinity());
  img.deep_rgb.assign(3 * n * L, 0.0f);
  img.deep_alpha.assign(n * L, 0.0f);
  for (size_t p = 0; p < n; ++p) {
    const float x = float(p % size_t(w)) / float(w), y = float(p / size_t(w)) / float(h);
    const bool hit = (p * 2654435761u) % 13 != 0;
    for (int c = 0; c < 3; ++c) {
      img.rgb[3 * p + c] = hit ? 0.5f + 0.5f * std::sin(17.0f * x + 5.0f * y * (c + 1)) : 0.0f;
      img.normal[3 * p + c] = hit ? std::cos(3.0f * x + c) : 0.0f;
    }
    img.depth_m[p] = hit ? 2.0f + x + 0.3f * std::sin(40.0f * y)
                         : std::numeric_limits<float>::infinity();
    img.uncertainty[p] = hit ? 0.01f + 0.001f * float(p % 7) : 0.0f;
    img.alpha[p] = hit && p % 5 != 0 ? 1.0f : 0.0f;
    img.layer_count[p] = hit ? uint8_t(1 + p % L) : 0;
    for (size_t l = 0; l < img.layer_count[p]; ++l) {
      img.deep_depth_m[p * L + l] = img.depth_m[p] + 0.5f * float(l);
      img.deep_alpha[p * L + l] = l == 0 ? img.alpha[p] : 1.0f;
      for (int c = 0; c < 3; ++c) {
        img.deep_rgb[3 * (p * L + l) + c] = img.rgb[3 * p + c] / float(l + 1);
      }
    }
  }
  return img;
}

/// The runs a ByteSink received, and the file they assemble into (each written at its offset).
struct Runs {
  std::vector<std::pair<int64_t, std::string>> runs;
  ByteSink Sink() {
    return [this](int64_t offset, std::string_view bytes) {
      runs.emplace_back(offset, std::string(bytes));
      return absl::OkStatus();
    };
  }
  std::string File() const {
    std::string file;
    for (const auto& [offset, bytes] : runs) {
      if (size_t(offset) + bytes.size() > file.size()) file.resize(size_t(offset) + bytes.size());
      std::memcpy(file.data() + offset, bytes.data(), bytes.size());
    }
    return file;
  }
  size_t Bytes() const {
    size_t n = 0;
    for (const auto& run : runs) n += run.second.size();
    return n;
  }
};

// Claim (§8 outputs, streamed): a RowEncoder fed a render's rows in bands, however they are
// split, sends runs that assemble (each at its offset) into exactly the file the whole-image
// encoder writes, for EXR, deep EXR and PNG; and it streams: by the time half the rows are in,
// the sink holds at least 40% of the file's bytes.
TEST(EncodeTest, RowEncoderStreamsTheSameFileInBands) {
  const RenderImage img = MakeLargeImage(512, 300, 3);
  const std::pair<ImageFormat, const char*> formats[] = {
      {ImageFormat::kExr, "EXR"}, {ImageFormat::kDeepExr, "deep EXR"}, {ImageFormat::kPng, "PNG"}};
  for (const auto& [format, name] : formats) {
    absl::StatusOr<std::string> whole = Encode(format, img);
    ASSERT_TRUE(whole.ok()) << name << ": " << whole.status();
    for (const std::vector<int>& cuts : {std::vector<int>{0, 16, 32, 150, 151, 300},
                                         std::vector<int>{0, 7, 100, 299, 300},
                                         std::vector<int>{0, 16, 40, 56, 64, 80, 96, 300}})
    for (const bool own_copies : {false, true}) {
      // own_copies: each band comes in an image of its own, gone when WriteRows returns, so an
      // encoder must copy what it holds back.
      Runs runs;
      auto encoder = RowEncoder::Create(format, img.width_px, img.height_px, runs.Sink());
      ASSERT_TRUE(encoder.ok()) << encoder.status();
      size_t at_half = 0;
      for (size_t c = 0; c + 1 < cuts.size(); ++c) {
        if (own_copies) {
          const auto band = std::make_unique<RenderImage>(img);
          ASSERT_TRUE((*encoder)->WriteRows(*band, cuts[c], cuts[c + 1]).ok()) << name;
        } else {
          ASSERT_TRUE((*encoder)->WriteRows(img, cuts[c], cuts[c + 1]).ok()) << name;
        }
        if (cuts[c + 1] <= img.height_px / 2) at_half = runs.Bytes();
      }
      const size_t before_finish = runs.runs.size();
      ASSERT_TRUE((*encoder)->Finish().ok()) << name;
      const std::string file = runs.File();
      std::printf("%s %dx%d in %zu bands%s: %zu bytes in %zu runs (%zu before finishing), "
                  "%.1f%% sent by the middle row, same file as whole: %d\n",
                  name, img.width_px, img.height_px, cuts.size() - 1,
                  own_copies ? " (each in its own image)" : "", file.size(),
                  runs.runs.size(), before_finish, 100.0 * double(at_half) / double(file.size()),
                  int(file == *whole));
      EXPECT_EQ(file.size(), whole->size()) << name;
      EXPECT_TRUE(file == *whole) << name;
      if (cuts[2] == 32) EXPECT_GE(double(at_half), 0.4 * double(file.size())) << name;
    }
  }
}

// Claim (ARCHITECTURE "Errors"): a RowEncoder refuses rows out of order and an early finish, and
// stops with the sink's own status when the sink refuses.
TEST(EncodeTest, RowEncoderRefusesDisorderAndStopsWithItsSink) {
  const RenderImage img = MakeLargeImage(64, 48, 1);
  Runs runs;
  auto encoder = RowEncoder::Create(ImageFormat::kExr, 64, 48, runs.Sink());
  ASSERT_TRUE(encoder.ok());
  EXPECT_EQ((*encoder)->WriteRows(img, 16, 32).code(), absl::StatusCode::kInvalidArgument);
  ASSERT_TRUE((*encoder)->WriteRows(img, 0, 16).ok());
  EXPECT_EQ((*encoder)->Finish().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(RowEncoder::Create(ImageFormat::kPng, 0, 4, runs.Sink()).status().code(),
            absl::StatusCode::kInvalidArgument);
  for (ImageFormat format : {ImageFormat::kExr, ImageFormat::kDeepExr, ImageFormat::kPng}) {
    int calls = 0;
    auto refusing = RowEncoder::Create(format, 64, 48, [&](int64_t, std::string_view) {
      return ++calls > 1 ? absl::UnavailableError("the reader went away") : absl::OkStatus();
    });
    ASSERT_TRUE(refusing.ok());
    absl::Status s = (*refusing)->WriteRows(img, 0, 48);
    if (s.ok()) s = (*refusing)->Finish();
    EXPECT_EQ(s.code(), absl::StatusCode::kUnavailable) << s;
  }
}

}  // namespace
}  // namespace vasl::render

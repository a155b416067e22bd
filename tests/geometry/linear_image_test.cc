// LinearToSrgb8 (how PNG renders are coded) against its definition, lround(255·LinearToSrgb);
// an 8-bit image packed as its codes (PackSrgb8) comes back bit for bit, and nothing else packs;
// a band of its rows (UnpackSrgb8Rows) reads as the whole image.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <limits>
#include <optional>
#include <utility>
#include <vector>

#include <gtest/gtest.h>

#include "lattice/geometry/linear_image.h"

namespace vasl::geometry {
namespace {

int Definition(float x) { return int(std::lround(LinearToSrgb(x) * 255.0f)); }

float OfBits(uint32_t bits) {
  float f;
  std::memcpy(&f, &bits, sizeof f);
  return f;
}

// Claim: the table-driven code equals the definition for every input: a stride through every
// float of [0, 1] (their bit patterns 0 to 0x3f800000, every 37th), the 256 floats on each
// side of each code's first float (where a table could be off), and the inputs outside (0, 1):
// negatives, zeros, NaN, infinities, values above 1, subnormals.
TEST(LinearImageTest, Srgb8CodeEqualsItsDefinitionEverywhere) {
  constexpr uint32_t kOne = 0x3f800000u;
  size_t checked = 0, wrong = 0;
  auto check = [&](float x) {
    ++checked;
    if (int(LinearToSrgb8(x)) != Definition(x)) {
      if (++wrong <= 5) {
        ADD_FAILURE() << "x = " << x << ": table " << int(LinearToSrgb8(x)) << ", definition "
                      << Definition(x);
      }
    }
  };
  for (uint32_t bits = 0; bits <= kOne; bits += 37) check(OfBits(bits));
  int first_of_code[256] = {};  // the least float of each code, by bisection
  size_t edges = 0;
  for (int b = 1; b <= 255; ++b) {
    uint32_t lo = 0, hi = kOne;
    while (hi - lo > 1) {
      const uint32_t mid = lo + (hi - lo) / 2;
      (Definition(OfBits(mid)) >= b ? hi : lo) = mid;
    }
    first_of_code[b] = int(hi);
    for (uint32_t bits = hi > 256 ? hi - 256 : 0; bits <= std::min(hi + 256, kOne); ++bits) {
      check(OfBits(bits));
      ++edges;
    }
  }
  const float outside[] = {-0.0f, 0.0f, -1.0f, -std::numeric_limits<float>::infinity(),
                           std::numeric_limits<float>::infinity(), std::nanf(""), 1.0f,
                           std::nextafter(1.0f, 2.0f), 7.5f, std::numeric_limits<float>::min(),
                           std::numeric_limits<float>::denorm_min(), 1e-30f};
  for (float x : outside) check(x);
  std::printf("sRGB 8-bit code: %zu inputs checked (%zu beside the 255 code edges; code 1 from "
              "%.9g, code 128 from %.9g, code 255 from %.9g), %zu differ from the definition\n",
              checked, edges, double(OfBits(uint32_t(first_of_code[1]))),
              double(OfBits(uint32_t(first_of_code[128]))),
              double(OfBits(uint32_t(first_of_code[255]))), wrong);
  EXPECT_EQ(wrong, 0u);
  EXPECT_EQ(LinearToSrgb8(std::nanf("")), 0);
  EXPECT_EQ(LinearToSrgb8(2.0f), 255);
}

// Claim: an image of every 8-bit code's linear value, in each channel count, packs into one
// code per value and unpacks bit for bit with its header; a value no code gives back exactly
// (a 16-bit code's, one nudged by an ulp, −0, NaN) leaves it unpacked.
TEST(LinearImageTest, AnImageOfSrgb8CodesPacksAndComesBackBitForBit) {
  for (int channels : {1, 3}) {
    LinearImage image;
    image.width_px = 256;
    image.height_px = 3;
    image.channels = channels;
    image.clip_value = 1.0f;
    for (int j = 0; j < image.height_px; ++j) {
      for (int i = 0; i < image.width_px; ++i) {
        for (int c = 0; c < channels; ++c) {
          image.pixels.push_back(Srgb8ToLinear()[size_t((i * (j + 1) + 37 * c) % 256)]);
        }
      }
    }
    const std::optional<Srgb8Image> packed = PackSrgb8(image);
    ASSERT_TRUE(packed.has_value()) << channels << " channels";
    EXPECT_EQ(packed->ByteSize(), image.pixels.size());
    EXPECT_EQ(packed->ByteSize() * 4, image.ByteSize());
    const LinearImage back = UnpackSrgb8(*packed);
    EXPECT_EQ(back.width_px, image.width_px);
    EXPECT_EQ(back.height_px, image.height_px);
    EXPECT_EQ(back.channels, channels);
    EXPECT_EQ(back.clip_value, 1.0f);
    ASSERT_EQ(back.pixels.size(), image.pixels.size());
    EXPECT_EQ(std::memcmp(back.pixels.data(), image.pixels.data(), image.ByteSize()), 0);

    const float not_codes[] = {SrgbToLinear(1000.0f / 65535.0f),
                               std::nextafter(Srgb8ToLinear()[128], 1.0f), -0.0f,
                               std::numeric_limits<float>::quiet_NaN()};
    for (float v : not_codes) {
      LinearImage changed = image;
      changed.pixels[image.pixels.size() / 2] = v;
      EXPECT_FALSE(PackSrgb8(changed).has_value()) << "value " << v;
    }
  }
}

// Claim: a band of an image (UnpackSrgb8Rows) holds its rows bit for bit, and a bilinear read
// within them is the whole image's read, at the image's edges too.
TEST(LinearImageTest, ABandReadsAsTheWholeImage) {
  LinearImage image;
  image.width_px = 37;
  image.height_px = 23;
  image.channels = 3;
  for (int i = 0; i < image.width_px * image.height_px * 3; ++i) {
    image.pixels.push_back(Srgb8ToLinear()[size_t((i * 37 + 11) % 256)]);
  }
  std::optional<Srgb8Image> packed = PackSrgb8(image);
  ASSERT_TRUE(packed.has_value());
  for (const auto& [begin, end] : std::vector<std::pair<int, int>>{{0, 23}, {0, 5}, {9, 14},
                                                                    {18, 23}, {-4, 40}}) {
    const LinearImage band = UnpackSrgb8Rows(*packed, begin, end);
    const int b = std::clamp(begin, 0, 23), e = std::clamp(end, 0, 23);
    EXPECT_EQ(band.row_origin, b);
    ASSERT_EQ(band.pixels.size(), size_t(e - b) * 37 * 3);
    EXPECT_EQ(band.HeldRows(), e - b);
    EXPECT_TRUE(std::equal(band.pixels.begin(), band.pixels.end(),
                           image.pixels.begin() + ptrdiff_t(size_t(b) * 37 * 3)));
    // Reads whose two rows lie in the band (v − ½ clamped to the image, and the next row).
    for (double v = -0.7; v <= 23.7; v += 0.35) {
      const int j0 = std::clamp(int(std::floor(v - 0.5)), 0, 22);
      const int j1 = std::clamp(int(std::floor(v - 0.5)) + 1, 0, 22);
      if (j0 < b || j1 >= e) continue;
      for (double u = -1.3; u <= 38.3; u += 0.9) {
        for (bool wrap : {false, true}) {
          float whole[3], from_band[3];
          SampleBilinear(image, u, v, wrap, whole);
          SampleBilinear(band, u, v, wrap, from_band);
          for (int c = 0; c < 3; ++c) ASSERT_EQ(whole[c], from_band[c]) << u << " " << v;
        }
      }
    }
  }
}

}  // namespace
}  // namespace vasl::geometry

#include "lattice/geometry/linear_image.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <cstring>
#include <limits>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_reduce.h>

#include "lattice/geometry/equirect.h"
#include "lattice/memory/huge_pages.h"

namespace vasl::geometry {

float SrgbToLinear(float c) {
  return c <= 0.04045f ? c / 12.92f : std::pow((c + 0.055f) / 1.055f, 2.4f);
}

float LinearToSrgb(float linear) {
  if (!(linear > 0.0f)) return 0.0f;  // also NaN
  if (linear >= 1.0f) return 1.0f;
  if (linear <= 0.0031308f) return 12.92f * linear;
  return 1.055f * std::pow(linear, 1.0f / 2.4f) - 0.055f;
}

namespace {

/// LinearToSrgb8's tables. The code of x, lround(255·LinearToSrgb(x)), does not decrease with
/// x, so it is the number of thresholds t_b ≤ x (t_b: the least float whose code is ≥ b,
/// b = 1..255, found by bisection over the floats' bit patterns, which order the positive
/// floats). Each run of floats sharing their top 16 bits (an exponent and 7 bits of mantissa:
/// the first code in `by_bucket`) meets at most one threshold: the curve's steepest slope
/// over such a run, near 1 or in the linear toe, is under half a code.
struct Srgb8Tables {
  static constexpr uint32_t kOneBits = 0x3f800000u;  // 1.0f
  std::array<float, 257> threshold{};                // t_b; t_256 = +inf
  std::array<uint8_t, (kOneBits >> 16) + 1> by_bucket{};

  static int Code(float x) { return int(std::lround(LinearToSrgb(x) * 255.0f)); }
  static float OfBits(uint32_t bits) {
    float f;
    std::memcpy(&f, &bits, sizeof f);
    return f;
  }

  Srgb8Tables() {
    threshold[0] = 0.0f;
    for (int b = 1; b <= 255; ++b) {
      uint32_t lo = 0, hi = kOneBits;  // Code(lo) < b ≤ Code(hi)
      while (hi - lo > 1) {
        const uint32_t mid = lo + (hi - lo) / 2;
        (Code(OfBits(mid)) >= b ? hi : lo) = mid;
      }
      threshold[size_t(b)] = OfBits(hi);
    }
    threshold[256] = std::numeric_limits<float>::infinity();
    for (uint32_t i = 0; i < by_bucket.size(); ++i) {
      by_bucket[i] = uint8_t(Code(OfBits(i << 16)));
    }
  }
};

}  // namespace

uint8_t LinearToSrgb8(float linear) {
  static const Srgb8Tables tables;
  if (!(linear > 0.0f)) return 0;  // also NaN
  if (linear >= 1.0f) return 255;
  uint32_t bits;
  std::memcpy(&bits, &linear, sizeof bits);
  const int code = tables.by_bucket[bits >> 16];
  return uint8_t(linear >= tables.threshold[size_t(code) + 1] ? code + 1 : code);
}

const std::array<float, 256>& Srgb8ToLinear() {
  static const std::array<float, 256> table = [] {
    std::array<float, 256> t;
    for (int code = 0; code < 256; ++code) t[size_t(code)] = SrgbToLinear(float(code) / 255.0f);
    return t;
  }();
  return table;
}

std::optional<Srgb8Image> PackSrgb8(const LinearImage& image) {
  if (!image.alpha.empty()) return std::nullopt;  // associated colour is not a code's value
  const std::array<float, 256>& table = Srgb8ToLinear();
  Srgb8Image out;
  out.header.width_px = image.width_px;
  out.header.height_px = image.height_px;
  out.header.channels = image.channels;
  out.header.clip_value = image.clip_value;
  out.header.coding = image.coding;
  const size_t n = image.pixels.size();
  memory::AssignOnHugePages(out.codes, n, uint8_t{0});
  const bool exact = tbb::parallel_reduce(
      tbb::blocked_range<size_t>(0, n, 1 << 16), true,
      [&](const tbb::blocked_range<size_t>& r, bool ok) {
        if (!ok) return false;
        for (size_t i = r.begin(); i != r.end(); ++i) {
          const float v = image.pixels[i];
          const uint8_t code = LinearToSrgb8(v);
          // Bit for bit: −0 or NaN do not come back from a code.
          if (std::memcmp(&table[code], &v, sizeof v) != 0) return false;
          out.codes[i] = code;
        }
        return true;
      },
      [](bool a, bool b) { return a && b; });
  if (!exact) return std::nullopt;
  return out;
}

LinearImage UnpackSrgb8(const Srgb8Image& packed) {
  return UnpackSrgb8Rows(packed, 0, packed.header.height_px);
}

LinearImage UnpackSrgb8Rows(const Srgb8Image& packed, int row_begin, int row_end) {
  const std::array<float, 256>& table = Srgb8ToLinear();
  LinearImage out = packed.header;
  const int H = packed.header.height_px;
  row_begin = std::clamp(row_begin, 0, H);
  row_end = std::clamp(row_end, row_begin, H);
  out.row_origin = row_begin;
  const size_t stride = size_t(packed.header.width_px) * size_t(packed.header.channels);
  const size_t first = size_t(row_begin) * stride, n = size_t(row_end - row_begin) * stride;
  out.pixels = memory::TakeFloatsForOverwrite(n);  // every value written below
  tbb::parallel_for(tbb::blocked_range<size_t>(0, n, 1 << 16),
                    [&](const tbb::blocked_range<size_t>& r) {
    for (size_t i = r.begin(); i != r.end(); ++i) out.pixels[i] = table[packed.codes[first + i]];
  });
  return out;
}

namespace {

// The bilinear read of a raster of `C` values per pixel (SampleBilinear's) of H rows, of which
// `data` holds `rows` from row `origin` (all H from 0 but for a band; rows outside it clamp to
// it).
void Bilinear(const float* data, int W, int H, int C, double u, double v, bool wrap, float* out,
              int origin, int rows) {
  const double x = u - 0.5, y = v - 0.5;
  const int i0 = int(std::floor(x)), j0 = int(std::floor(y));
  const double fx = x - i0, fy = y - j0;
  const int ia = wrap ? WrapColumn(i0, W) : std::clamp(i0, 0, W - 1);
  const int ib = wrap ? WrapColumn(i0 + 1, W) : std::clamp(i0 + 1, 0, W - 1);
  const int last = rows - 1;
  const int ja = std::max(0, std::min(std::clamp(j0, 0, H - 1) - origin, last));
  const int jb = std::max(0, std::min(std::clamp(j0 + 1, 0, H - 1) - origin, last));
  const float* p00 = &data[(size_t(ja) * W + ia) * C];
  const float* p10 = &data[(size_t(ja) * W + ib) * C];
  const float* p01 = &data[(size_t(jb) * W + ia) * C];
  const float* p11 = &data[(size_t(jb) * W + ib) * C];
  for (int c = 0; c < C; ++c) {
    out[c] = float((1 - fy) * ((1 - fx) * p00[c] + fx * p10[c]) + fy * ((1 - fx) * p01[c] + fx * p11[c]));
  }
}

}  // namespace

int LinearImage::HeldRows() const {
  const size_t row = size_t(std::max(width_px, 0)) * size_t(std::max(channels, 0));
  if (pixels.size() == row * size_t(std::max(height_px, 0))) return height_px;  // whole
  return row > 0 ? int(pixels.size() / row) : 0;
}

void SampleBilinear(const LinearImage& img, double u, double v, bool wrap, float* out) {
  Bilinear(img.pixels.data(), img.width_px, img.height_px, img.channels, u, v, wrap, out,
           img.row_origin, img.HeldRows());
}

float SampleCoverage(const LinearImage& img, double u, double v, bool wrap) {
  if (img.alpha.empty()) return 1.0f;
  float a;
  Bilinear(img.alpha.data(), img.width_px, img.height_px, 1, u, v, wrap, &a, img.row_origin,
           img.HeldRows());
  return a;
}

float SampleCovered(const LinearImage& img, double u, double v, bool wrap, float* out) {
  SampleBilinear(img, u, v, wrap, out);
  const float a = SampleCoverage(img, u, v, wrap);
  if (a < 1.0f) {
    for (int c = 0; c < img.channels; ++c) out[c] = a > 0.0f ? out[c] / a : 0.0f;
  }
  return a;
}

}  // namespace vasl::geometry

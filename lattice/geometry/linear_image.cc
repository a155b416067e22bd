#include "lattice/geometry/linear_image.h"

#include <algorithm>
#include <cmath>
#include <cstddef>

#include "lattice/geometry/equirect.h"

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

void SampleBilinear(const LinearImage& img, double u, double v, bool wrap, float* out) {
  const double x = u - 0.5, y = v - 0.5;
  const int i0 = int(std::floor(x)), j0 = int(std::floor(y));
  const double fx = x - i0, fy = y - j0;
  const int W = img.width_px, H = img.height_px, C = img.channels;
  const int ia = wrap ? WrapColumn(i0, W) : std::clamp(i0, 0, W - 1);
  const int ib = wrap ? WrapColumn(i0 + 1, W) : std::clamp(i0 + 1, 0, W - 1);
  const int ja = std::clamp(j0, 0, H - 1), jb = std::clamp(j0 + 1, 0, H - 1);
  const float* p00 = &img.pixels[(size_t(ja) * W + ia) * C];
  const float* p10 = &img.pixels[(size_t(ja) * W + ib) * C];
  const float* p01 = &img.pixels[(size_t(jb) * W + ia) * C];
  const float* p11 = &img.pixels[(size_t(jb) * W + ib) * C];
  for (int c = 0; c < C; ++c) {
    out[c] = float((1 - fy) * ((1 - fx) * p00[c] + fx * p10[c]) + fy * ((1 - fx) * p01[c] + fx * p11[c]));
  }
}

}  // namespace vasl::geometry

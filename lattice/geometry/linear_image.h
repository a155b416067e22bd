/// @file linear_image.h
/// @brief A decoded image in linear radiometry and its bilinear read at continuous pixel
///        coordinates (§2.1: pixel centres at half-integers): one implementation for the ingest
///        samplers (§4) and the render's colour detail (§8).
#pragma once

#include <cstddef>
#include <vector>

namespace vasl::geometry {

/// A decoded image, row-major, row 0 at the top, linear radiometry.
struct LinearImage {
  int width_px = 0;
  int height_px = 0;
  int channels = 0;            ///< 1 or 3
  std::vector<float> pixels;   ///< width·height·channels values
  float clip_value = 0.0f;     ///< linear value at which the encoding clips (1 for 8/16-bit); 0: none

  /// Bytes its pixels take.
  std::size_t ByteSize() const { return pixels.size() * sizeof(float); }
};

/// Bilinear read of `img` at continuous pixel coordinates (u, v): `img.channels` values into
/// `out`. Columns wrap across the seam (`wrap`, a panorama) or clamp, rows clamp. (Saturation
/// is read from its own map, ingest::DetectSaturation.)
void SampleBilinear(const LinearImage& img, double u, double v, bool wrap, float* out);

}  // namespace vasl::geometry

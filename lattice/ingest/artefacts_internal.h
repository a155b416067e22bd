/// @file artefacts_internal.h
/// @brief What the §9 detectors share (artefacts.cc): the clip level, the clipped blobs that
///        are saturation's regions and flare's sources, and the thresholds they agree on.
#pragma once

#include <algorithm>
#include <cstdint>
#include <vector>

#include "lattice/geometry/linear_image.h"

namespace vasl::ingest::internal {

/// The clip fraction at and above which a channel is clipped.
inline constexpr float kClipFraction = 0.999f;
/// A pixel whose artefact (bloom, glare) adds more than this share to its own light is
/// affected *(choice)*: less is within what exposure and texture vary by.
inline constexpr double kAffectedShare = 0.1;
/// Light below this fraction of the clip level (2.5 codes of an 8-bit image) is the sensor's
/// and the codec's noise.
inline constexpr double kNoise = 0.01;
/// Directions around a source in which its surround is measured apart: an artefact spreads
/// alike in every direction, scene content does not.
inline constexpr int kSectors = 8;
/// The quantile of a ring's pixels that measures spilled light: an artefact lifts a ring's
/// darkest pixels as much as its brightest, while texture leaves them at the surround's
/// darkest level.
inline constexpr double kRingQuantile = 0.1;

/// Pixel p's brightest channel over the image's clip level (clip_value > 0).
inline float Level(const geometry::LinearImage& image, size_t p) {
  float m = 0.0f;
  const float inv_clip = 1.0f / image.clip_value;
  for (int c = 0; c < image.channels; ++c) {
    m = std::max(m, image.pixels[p * size_t(image.channels) + size_t(c)] * inv_clip);
  }
  return m;
}

/// A confidence map of a width_px × height_px image at 1 everywhere (one channel).
inline geometry::LinearImage ConfidenceOnes(int width_px, int height_px) {
  geometry::LinearImage map;
  map.width_px = width_px;
  map.height_px = height_px;
  map.channels = 1;
  map.pixels.assign(size_t(width_px) * size_t(height_px), 1.0f);
  return map;
}

/// The clipped pixels of an image and their 8-connected blobs (columns wrap on a panorama).
struct ClippedBlobs {
  int64_t clipped_pixels = 0;
  std::vector<uint8_t> clipped;  ///< per pixel; empty when no pixel is clipped
  std::vector<int32_t> label;    ///< per pixel, its blob; −1 off the blobs
  std::vector<int64_t> area;     ///< per blob, pixels
  std::vector<int> box_x0, box_x1, box_y0, box_y1;  ///< per blob, its pixel box
  /// Per blob, its centroid (pixel centres; across a panorama's seam x may lie outside [0, W)).
  std::vector<double> centre_x, centre_y;
  size_t size() const { return area.size(); }
};

/// Finds the clipped pixels (a channel at ≥ kClipFraction of the clip level) and their blobs;
/// empty for an image without a clip level or of inconsistent size. Parallel over pixels.
ClippedBlobs FindClippedBlobs(const geometry::LinearImage& image, bool wrap);

/// The radius R_b (pixels) within which a blob of `area` pixels spills bloom: 4·r_b + 8 with
/// r_b = √(area/π), capped at a quarter of the image height (at least 8).
int BloomReachPx(int64_t area, int height_px);

}  // namespace vasl::ingest::internal

namespace vasl::ingest {
struct SaturationMap;
struct FlareMap;
/// DetectSaturation, DetectFlare and DetectSmear over blobs already found (DetectArtefacts).
SaturationMap DetectSaturation(const geometry::LinearImage& image,
                               const internal::ClippedBlobs& blobs);
FlareMap DetectFlare(const geometry::LinearImage& image, const internal::ClippedBlobs& blobs,
                     bool wrap);
struct SmearMap;
SmearMap DetectSmear(const geometry::LinearImage& image, const internal::ClippedBlobs& blobs,
                     bool wrap);
}  // namespace vasl::ingest

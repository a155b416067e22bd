/// @file artefacts.h
/// @brief Sensor artefacts as per-pixel confidence (VASL-MODEL §9), found in a decoded image
///        and sampled into its records' confidence factors at ingest.
#pragma once

#include <cstdint>
#include <string>

#include "absl/status/statusor.h"

#include "lattice/geometry/linear_image.h"

namespace vasl::ingest {

/// Saturation and blooming (§9) found in one image.
struct SaturationMap {
  /// Per pixel, the confidence that its value is its surface's own light: 0 where a channel is
  /// at the clip level (≥ 0.999 of it), 1 − Δ/L in a bloom halo (Δ the bloom, L the pixel's
  /// brightest channel over the clip level), 1 elsewhere; one channel. No pixels: 1 everywhere
  /// (nothing clipped, or no clip level).
  geometry::LinearImage conf;
  int64_t clipped_pixels = 0;
  int64_t halo_pixels = 0;  ///< pixels outside the clipped regions with confidence < 1
  int blobs = 0;            ///< connected clipped regions (8-neighbours)
  int max_halo_radius_px = 0;

  /// Share of the image's pixels with confidence < 1.
  double CoveredFraction(int width_px, int height_px) const;
};

/// Finds saturation and blooming (§9) in `image` (linear, with its clip level).
/// @details A pixel is clipped when any channel reaches 0.999 of the clip level. Clipped pixels
///          form blobs (8-connected). Around each blob the light a sensor spills (blooming, and
///          the optics' veiling near a source) is measured, not assumed: every pixel within
///          R_b = 4·r_b + 8 pixels of the blob (r_b = √(area/π), capped at a quarter of the
///          image height) falls into the ring ⌊distance⌋ of its nearest clipped pixel (an exact
///          Euclidean distance transform). A ring's 10% quantile of brightness, made
///          non-increasing outward, is the blob's radial profile; its excess over the lowest
///          ring (the surround's own level) is the ring's bloom Δ_k, counted above 0.01 of the
///          clip (noise). Bloom lifts a ring's darkest pixels as much as its brightest, while
///          texture leaves them at the surround's darkest level: so texture that does not fall
///          off around a blob is not taken for bloom, and the halo grows with how far the
///          source is over the clip level, as the image shows it. A pixel whose bloom adds more
///          than a tenth to its own light (1 − Δ/L < 1/1.1) is halo, with confidence 1 − Δ/L.
///          At most 16 M (ring, direction) bins are measured, the largest blobs first: an
///          image speckled with clipped specks beyond them keeps those specks at 0, without
///          halos, in bounded memory.
///          Columns wrap across a panorama's seam for the blobs (`wrap`); the distance
///          transform does not (a halo cut at the seam is measured on its own side).
///          Exposure (a halo's growth with exposure time) is in the image already; column
///          smear is not modelled.
/// Parallel over rows and columns (TBB).
SaturationMap DetectSaturation(const geometry::LinearImage& image, bool wrap);

/// A confidence map (one channel in [0, 1]; empty: 1 everywhere) of a width_px × height_px
/// image as an 8-bit grey PNG for a person to look at: 255 where the confidence is 1, 0 where
/// it is 0.
absl::StatusOr<std::string> EncodeConfidencePng(const geometry::LinearImage& conf, int width_px,
                                                int height_px);

}  // namespace vasl::ingest

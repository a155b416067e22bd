/// @file backproject.h
/// @brief Back-projection of RGBZ images into derived records (VASL-MODEL §10).
#pragma once

#include <cstdint>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "lattice/ingest/sources.h"
#include "lattice/records/records.h"

namespace vasl::ingest {

/// Decodes an OpenEXR (or any float image OpenImageIO reads) whose channels are named like a
/// render's: R, G, B and Z are required; N.x, N.y, N.z, U and A are used when present. A deep
/// OpenEXR (a deep render: each pixel's successive surfaces, R, G, B, Z and A per sample) keeps
/// every sample (DerivedImage::sample_pixel).
/// INVALID_ARGUMENT when a required channel is missing or the bytes do not decode;
/// RESOURCE_EXHAUSTED above `max_pixels` pixels (a deep image: samples) or 16 channels.
absl::StatusOr<DerivedImage> DecodeRgbzImage(std::string_view bytes, int64_t max_pixels);

/// What BackProjectRecords found, in pixels (a deep image: samples).
struct BackProjectStats {
  int64_t pixels_used = 0;     ///< finite Z, covered, landing in a vossel of the lattice
  int64_t pixels_outside = 0;  ///< finite Z whose point lies in no vossel (no geometry there)
  int64_t pixels_empty = 0;    ///< no surface (Z not finite) or not covered (A = 0)
  int64_t pixels_invalid = 0;  ///< a surface (finite Z, covered) whose R, G or B is NaN or ±inf
};

/// §10: for each pixel with finite Z (and A > 0 when the image has A), x = o + Z·d with d the
/// pixel-centre ray of the source's projection; the vossel k holding x gets the pixel. One
/// derived record per vossel averages its pixels (in pixel order, so the result is the same
/// bits every time): value = mean C, range = mean Z, cosθ = mean |N·d| with the image's normals
/// or |n_k·d| with the vossel's (1 when it has none), footprint from the pixel's angle (§3),
/// uv = mean pixel centre, V = 1, confidence factors 1 but conf[codec] = 1/(1 + U/0.1)
/// *(choice: U in the slot an edited image's own quality takes)*, flags derived, modality
/// derived. A deep image back-projects every sample of each pixel the same way (each layer
/// lands on its own surface's vossel). With `only` (a flag per vossel) other vossels get no
/// record. Parallel (TBB).
records::RecordSet BackProjectRecords(const records::VosselGeometry& geometry,
                                      const DerivedSource& source,
                                      const std::vector<uint8_t>* only = nullptr,
                                      BackProjectStats* stats = nullptr);

}  // namespace vasl::ingest

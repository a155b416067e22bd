/// @file render.h
/// @brief The VASL rendering equation (VASL-MODEL §8): an equirectangular RGBZ + normal +
///        uncertainty image from any pose, by hierarchical DDA over the lattice.
#pragma once

#include <cstdint>
#include <vector>

#include "absl/status/statusor.h"
#include "lattice/geometry/pose.h"
#include "lattice/records/records.h"

namespace vasl::render {

/// What to render (§8).
struct RenderRequest {
  geometry::Pose pose;          ///< T_world_camera of the virtual panorama
  int width_px = 2048;
  int height_px = 1024;
  int64_t version = 0;          ///< 0: HEAD
  double eta = 0.0;             ///< view term η (§8); 0 uses the fused colour C_k
  double max_range_m = 1000.0;  ///< rays stop here
};

/// A rendered equirectangular RGBZ + normal + uncertainty image (§8), row-major, row 0 up.
struct RenderImage {
  int width_px = 0;
  int height_px = 0;
  int64_t version = 0;
  std::vector<float> rgb;          ///< 3 per pixel, linear; 0 where no hit
  std::vector<float> depth_m;      ///< 1 per pixel: range along the ray; +inf where no hit
  std::vector<float> normal;       ///< 3 per pixel, world frame; 0 where no hit
  std::vector<float> uncertainty;  ///< 1 per pixel: U_k; 0 where no hit
  int64_t hit_pixels = 0;
};

/// Renders `request` from a version's geometry and fused values (§8). Parallel over rows (TBB).
/// INVALID_ARGUMENT for a non-positive size.
absl::StatusOr<RenderImage> RenderEquirect(const records::VosselGeometry& geometry,
                                           const records::FusedValues& fused,
                                           const RenderRequest& request);

}  // namespace vasl::render

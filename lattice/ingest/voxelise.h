/// @file voxelise.h
/// @brief Voxelisation of LiDAR returns into vossels and their normals (VASL-MODEL §1).
#pragma once

#include <cmath>
#include <vector>

#include "absl/status/statusor.h"
#include "lattice/ingest/sources.h"
#include "lattice/records/records.h"

namespace vasl::ingest {

/// Largest |index| of a vossel coordinate on any axis (keys pack 21 bits per axis).
inline constexpr int kMaxVosselIndex = (1 << 20) - 1;

/// §1: the vossel holding world point x, k = round(x / h) per axis (cell-centred), as doubles so
/// that callers can check the range before converting. Points are binned in float world
/// coordinates everywhere, so that every return finds the vossel BuildGeometry made for it.
inline Eigen::Vector3d VosselIndexOf(const Eigen::Vector3f& x_world, double vossel_size_m) {
  return {std::round(x_world.x() / vossel_size_m), std::round(x_world.y() / vossel_size_m),
          std::round(x_world.z() / vossel_size_m)};
}

/// §1: bins every return of every LiDAR into the vossel k = round(x / h) (cell-centred), and
/// gives each vossel its point count, centroid, covariance and a PCA normal over its 3×3×3
/// neighbourhood (the pooled scatter of the neighbours' points), oriented toward the mean
/// direction of the sensors that saw it. Returns at sensor-frame (0,0,0) (a scanner's "no
/// return" marker) are skipped. Vossels come in canonical order (records::
/// CanonicalizeVosselOrder). Parallel (TBB). INVALID_ARGUMENT when a point falls outside the
/// lattice's range (±kMaxVosselIndex·h).
absl::StatusOr<records::VosselGeometry> BuildGeometry(const std::vector<LidarSource>& lidars,
                                                      double vossel_size_m);

/// Recomputes `geometry.normal` by PCA over each vossel's 3×3×3 neighbourhood; `view_sum` (one
/// per vossel, may be empty) orients each normal toward the sensors; a vossel with too few
/// neighbours for a plane gets its view direction as normal.
void ComputeNormals(records::VosselGeometry& geometry,
                    const std::vector<Eigen::Vector3f>& view_sum);

}  // namespace vasl::ingest

/// @file voxelise.h
/// @brief Voxelisation of LiDAR returns into vossels and their normals (VASL-MODEL §1).
#pragma once

#include <cmath>
#include <memory>
#include <vector>

#include "absl/status/statusor.h"
#include "lattice/ingest/sources.h"
#include "lattice/records/records.h"

namespace vasl::ingest {

/// Largest |index| of a vossel coordinate on any axis (keys pack 21 bits per axis).
inline constexpr int kMaxVosselIndex = (1 << 20) - 1;

/// §1: the lattice-frame position of a sensor-frame return p under the pose (R, o), in
/// double. Every binning of a return computes it here, so that each return finds the vossel
/// BinLidar made for it; in double, moving the origin by whole metres moves every position by
/// exactly that (a georeferenced copy of a site bins as the site does).
inline Eigen::Vector3d ReturnPosition(const Eigen::Matrix3d& R, const Eigen::Vector3d& o,
                                      const float* p) {
  return R * Eigen::Vector3d(p[0], p[1], p[2]) + o;
}

/// §1: the vossel holding lattice point x, k = round(x / h) per axis (cell-centred), as
/// doubles so that callers can check the range before converting.
inline Eigen::Vector3d VosselIndexOf(const Eigen::Vector3d& x, double vossel_size_m) {
  return {std::round(x.x() / vossel_size_m), std::round(x.y() / vossel_size_m),
          std::round(x.z() / vossel_size_m)};
}

/// One LiDAR's returns binned into vossels (§1): per vossel its point count and exact sums
/// (records::VosselSums), vossels in coordinate order.
struct BinnedLidar {
  std::vector<openvdb::Coord> coord;      ///< index-space k of each vossel hit
  std::vector<int32_t> count;             ///< returns in it
  std::vector<records::VosselSums> sums;  ///< their sums relative to h·k
  /// The gap-fill points binned with the returns (null without a range grid): set them as the
  /// LiDAR's `gap_fill` so that its records do not compute them again.
  std::shared_ptr<const GapFillPoints> fill;
  size_t size() const { return coord.size(); }
};

/// Surface connectivity from a range grid (choice; issue "Renders…", "no see-through gaps"):
/// grid-neighbouring returns whose ranges differ by at most this share lie on one surface.
inline constexpr double kGapFillRangeStep = 0.1;
/// Triangles of such returns with an edge longer than this many vossels are not bridged (a gap
/// that wide is more likely an opening than a surface the scanner sampled sparsely).
inline constexpr double kGapFillMaxEdgeVossels = 8.0;
/// Spacing of the fill points on a bridged triangle, vossels.
inline constexpr double kGapFillStepVossels = 0.5;

/// §1: bins every return of `lidar` into the vossel k = round(x / h) (cell-centred). Returns at
/// sensor-frame (0,0,0) (a scanner's "no return" marker) are skipped. Within a vossel the
/// points are summed in point order, so the result does not depend on the thread count.
/// With a range grid (LidarSource::HasGrid), each pair of triangles between grid-neighbouring
/// returns (a cell, its right, lower and lower-right neighbours) whose ranges differ by at most
/// kGapFillRangeStep and whose longest edge lies in (h, kGapFillMaxEdgeVossels·h] is sampled
/// every kGapFillStepVossels·h; the samples that fall in vossels holding none of the scan's
/// returns join them as gap-fill points (counted and summed like returns, after them), so a
/// surface the scan sampled more sparsely than the lattice has no holes for rays to pass. The
/// LiDAR's records sample them too, each the returns of its triangle interpolated (GapFill).
/// Parallel (TBB). INVALID_ARGUMENT when a point falls outside the lattice's range
/// (±kMaxVosselIndex·h).
absl::StatusOr<BinnedLidar> BinLidar(const LidarSource& lidar, double vossel_size_m);

/// The gap-fill points of a LiDAR with a range grid (GapFillPoints), as BinLidar computes them;
/// empty for a LiDAR without a grid. Its cache `lidar.gap_fill` when that is set.
std::shared_ptr<const GapFillPoints> GapFill(const LidarSource& lidar, double vossel_size_m);

/// An empty geometry of vossel size h with an (empty) index grid and sums.
records::VosselGeometry EmptyGeometry(double vossel_size_m);

/// What MergeBinned changed.
struct MergeResult {
  std::vector<int32_t> old_to_new;  ///< new index of each vossel `geometry` had before
  std::vector<uint8_t> touched;     ///< per vossel of the result: 1 where the sums changed
  size_t new_vossels = 0;           ///< vossels the merge created
};

/// Adds one LiDAR's binned returns into `geometry`: counts and sums of the vossels it hit grow
/// (existing sums + the LiDAR's, in that order: merging scans in source-id order gives the same
/// bits whatever the grouping), new vossels are created with this LiDAR's returns as their
/// record frame (records::VosselFrame; an existing vossel keeps its frame), and the vossels are
/// renumbered in canonical order. Centroids, covariances and normals are not updated (see
/// DeriveCentroidAndCovariance, ComputeNormals). `geometry` must carry sums.
MergeResult MergeBinned(records::VosselGeometry& geometry, const BinnedLidar& add);
/// The same, leaving `base` as it is and writing the merge to `out` (not `&base`): base's
/// arrays are read once (records::InsertVossels), not copied first.
MergeResult MergeBinned(const records::VosselGeometry& base, const BinnedLidar& add,
                        records::VosselGeometry* out);

/// §1, the whole path: every LiDAR binned and merged in the given order (callers pass source-id
/// order), centroids and covariances derived, and a PCA normal for every vossel over its
/// 3×3×3 neighbourhood (ComputeNormals). Vossels come in canonical order (records::
/// CanonicalizeVosselOrder). Parallel (TBB). INVALID_ARGUMENT as BinLidar.
absl::StatusOr<records::VosselGeometry> BuildGeometry(const std::vector<LidarSource>& lidars,
                                                      double vossel_size_m);

/// Computes `geometry.normal` by PCA over each vossel's 3×3×3 neighbourhood (the pooled scatter
/// of the neighbours' points), oriented toward the sensors that saw it (the sums' view_sum); a
/// vossel with too few neighbours for a plane gets its view direction as normal. The frames'
/// normals (when the geometry has frames) the same way over the neighbours' frames. With `only`
/// (one flag per vossel) just the flagged vossels are recomputed and the others keep their
/// normal; a vossel's normal depends only on its neighbourhood's counts and sums, so a partial
/// recompute gives the same bits as a full one. `normal` is sized to the vossels first.
void ComputeNormals(records::VosselGeometry& geometry, const std::vector<uint8_t>* only = nullptr);

}  // namespace vasl::ingest

/// @file tiling.h
/// @brief Spatial tiles of the lattice (ARCHITECTURE.md "Storage of one project"): tile keys,
///        their world boxes, the angular cap a tile covers from a sensor, and a sensor's coarse
///        reach raster. These decide which (source, tile) pairs an incremental ingest must
///        revisit (VASL-MODEL §5: "visibility is recomputed only for (scan, region) pairs whose
///        depth panorama the new geometry changes").
/// @details A tile holds the vossels k with floor(k / T) = key on each axis, T the project's
///          tile edge in vossels. Its world box covers the cells of those vossels:
///          [(T·key − ½)·h, (T·(key+1) − ½)·h] per axis (vossel centres at h·k, §1), so every
///          centroid of the tile lies inside it.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <string>
#include <vector>

#include <Eigen/Core>
#include <openvdb/openvdb.h>

#include "absl/status/statusor.h"
#include "lattice/geometry/equirect.h"
#include "lattice/geometry/pose.h"

namespace vasl::tiles {

/// Default tile edge in vossels (64³ vossels: 3.2 m at h = 5 cm, 1.28 m at h = 2 cm). Of 32, 64
/// and 128 it writes the fewest bytes over a 12-scan site (README "Storage"). A project setting.
inline constexpr int kDefaultTileVossels = 64;

/// Integer coordinates of a tile.
struct TileKey {
  int32_t x = 0, y = 0, z = 0;
  bool operator<(const TileKey& o) const {
    return x != o.x ? x < o.x : (y != o.y ? y < o.y : z < o.z);
  }
  bool operator==(const TileKey& o) const { return x == o.x && y == o.y && z == o.z; }
  bool operator!=(const TileKey& o) const { return !(*this == o); }
};

/// "x_y_z", as tile objects are listed.
std::string ToString(const TileKey& key);

/// The tile of vossel k (floor division per axis).
inline TileKey TileOf(const openvdb::Coord& k, int tile_vossels) {
  auto fdiv = [tile_vossels](int a) {
    return a >= 0 ? a / tile_vossels : -((-a + tile_vossels - 1) / tile_vossels);
  };
  return {fdiv(k.x()), fdiv(k.y()), fdiv(k.z())};
}

/// World box of a tile (see @details), metres.
struct Box {
  Eigen::Vector3d min_m = Eigen::Vector3d::Zero();
  Eigen::Vector3d max_m = Eigen::Vector3d::Zero();
};
Box BoxOf(const TileKey& key, int tile_vossels, double vossel_size_m);

/// The directions and ranges at which a box appears from a sensor at `o`: a cone of half-angle
/// `half_angle_rad` about `dir` (the box's bounding sphere, grown by `grow_m`), and the nearest
/// and farthest distance from `o` to the box itself. `everywhere` when `o` lies inside the grown
/// sphere (the box may appear in any direction).
struct ViewCap {
  Eigen::Vector3d dir = Eigen::Vector3d::UnitX();  ///< unit, world frame
  double half_angle_rad = 0.0;
  double near_m = 0.0;  ///< distance from o to the box (0 inside)
  double far_m = 0.0;   ///< distance from o to the box's farthest corner
  bool everywhere = false;
};
ViewCap CapOf(const Box& box, const Eigen::Vector3d& o_world, double grow_m);

/// True when two caps seen from the same sensor may share a direction, up to `margin_rad`.
bool CapsOverlap(const ViewCap& a, const ViewCap& b, double margin_rad);

/// A sensor's reach: per cell of a coarse equirect raster (in the sensor frame, §2.1), an upper
/// bound of the depth panorama's range over the cell's pixels (+inf where nothing is in the
/// way). A tile whose cap meets no cell reaching its near distance is hidden from the sensor.
struct ReachRaster {
  geometry::EquirectSize size;   ///< raster size (cells)
  std::vector<float> max_depth_m;  ///< row-major, row 0 up
};

/// Pixels of a depth panorama per reach cell along each axis.
inline constexpr int kReachBlockPx = 16;

/// The reach raster of a depth panorama (`depth_m` row-major over `size`): per block of
/// kReachBlockPx² pixels, the maximum depth. With `cells` (a flag per cell, row-major over the
/// raster) only the flagged cells are computed, at their cost alone, and every other cell holds
/// `elsewhere` (a revisit's panorama, which holds nothing outside its flagged cells); `cells`
/// of another count are taken as none.
ReachRaster ReachFromDepth(const std::vector<float>& depth_m, const geometry::EquirectSize& size,
                           const std::vector<uint8_t>* cells = nullptr, float elsewhere = 0.0f);

/// Per block of kReachBlockPx² pixels of a depth panorama, the minimum depth, row-major over
/// the raster ReachFromDepth makes. Pixel rows outside [row_begin, row_end) count as +inf.
std::vector<float> CellMinFromDepth(const std::vector<float>& depth_m,
                                    const geometry::EquirectSize& size, int row_begin = 0,
                                    int row_end = -1);

/// True when some cell of `reach` that `cap` (world frame; the sensor at `T_world_sensor`) may
/// cover holds a depth ≥ `min_depth_m`: the sensor may see something at that range in the cap.
/// Conservative: cells are tested by their centre direction and angular half-diagonal.
bool Reaches(const ReachRaster& reach, const geometry::Pose& T_world_sensor, const ViewCap& cap,
             double min_depth_m);

/// The pixels of an equirect raster of `size` (§2.1) whose centres may lie within `radius_rad`
/// of the unit direction `d_sensor` (sensor frame), one pixel of slack on every side: rows
/// `row_first` to `row_last`, and `col_count` columns from `col_first` (in [0, W), wrapping
/// across the seam). A cap of radius α clear of both poles spans the azimuths within
/// asin(sin α / cos ψ_c) of its centre's; one touching a pole spans every column.
struct PixelSpan {
  int row_first = 0, row_last = -1, col_first = 0, col_count = 0;
};
PixelSpan CapPixelSpan(const Eigen::Vector3d& d_sensor, double radius_rad,
                       const geometry::EquirectSize& size);

/// The cells of a raster of `size` cells (reach cells, or any equirect raster in the frame of a
/// sensor at `T_world_sensor`) that a cap may overlap, each tested by its centre direction and
/// its angular half-diagonal as Reaches tests it; for rules that test many caps against one
/// raster. A cap clear of the poles is searched over the columns its azimuth span can reach.
class CapCells {
 public:
  CapCells(const geometry::EquirectSize& size, const geometry::Pose& T_world_sensor);
  const geometry::EquirectSize& size() const { return size_; }
  size_t cell_count() const {
    return size_t(std::max(0, size_.width_px)) * size_t(std::max(0, size_.height_px));
  }
  /// Calls fn(cell, whole) for every cell `cap` may overlap (cell: row-major index; whole: the
  /// cell lies wholly inside the cap) until fn returns false.
  template <typename Fn>
  void ForEach(const ViewCap& cap, Fn&& fn) const;
  /// True when a cell `cap` may overlap bounds a depth of at least `min_depth_m`
  /// (`max_depth_m`: a reach raster's bounds over these cells), as Reaches decides it.
  bool Reaches(const ViewCap& cap, const std::vector<float>& max_depth_m,
               double min_depth_m) const;

 private:
  geometry::EquirectSize size_;
  Eigen::Matrix3d R_sensor_world_;
  double half_diag_ = 0.0;
  std::vector<Eigen::Vector3d> dir_;  ///< cell centres' unit directions, sensor frame
};

/// How the union of `caps` (world frame; the sensor at `T_world_sensor`) covers each cell of a
/// raster of `size` cells: 2 when the whole cell lies inside a cap, 1 when it may overlap one,
/// 0 when it lies outside every cap.
std::vector<uint8_t> CellCoverage(const geometry::EquirectSize& size,
                                  const geometry::Pose& T_world_sensor,
                                  const std::vector<ViewCap>& caps);

/// A reach raster recomputed from a depth panorama that splatted only the vossels of a cone
/// (exact inside it, an upper bound elsewhere, since splats only lower a depth), merged into
/// the previous one, which still bounds the depths outside the cone: cells wholly inside the
/// cone (coverage 2) take the fresh value, cells on its edge (1) the larger of both, cells
/// outside (0) the smaller. Both rasters must have the same size.
ReachRaster MergeReach(const ReachRaster& old, const ReachRaster& fresh,
                       const std::vector<uint8_t>& coverage);

/// Bytes of a reach raster as stored (little-endian: magic "VRCH", width, height, floats).
std::string SerializeReach(const ReachRaster& reach);
/// DATA_LOSS when `bytes` is not a reach raster.
absl::StatusOr<ReachRaster> ParseReach(const std::string& bytes);

template <typename Fn>
void CapCells::ForEach(const ViewCap& cap, Fn&& fn) const {
  const int W = size_.width_px, H = size_.height_px;
  if (W <= 0 || H <= 0) return;
  if (cap.everywhere) {
    for (size_t c = 0; c < cell_count(); ++c) {
      if (!fn(c, true)) return;
    }
    return;
  }
  const Eigen::Vector3d d = R_sensor_world_ * cap.dir;
  const double outer = cap.half_angle_rad + half_diag_;
  const double cos_outer = std::cos(std::min(outer, M_PI));
  const double inner = cap.half_angle_rad - half_diag_;
  const double cos_inner = inner > 0.0 ? std::cos(inner) : 2.0;  // 2: no cell wholly inside
  const PixelSpan span = CapPixelSpan(d, outer, size_);
  for (int j = span.row_first; j <= span.row_last; ++j) {
    const size_t row = size_t(j) * size_t(W);
    for (int n = 0, i = span.col_first; n < span.col_count; ++n, i = i + 1 == W ? 0 : i + 1) {
      const double c = dir_[row + size_t(i)].dot(d);
      if (c >= cos_outer && !fn(row + size_t(i), c >= cos_inner)) return;
    }
  }
}

}  // namespace vasl::tiles

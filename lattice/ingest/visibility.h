/// @file visibility.h
/// @brief Depth panoramas and fractional visibility with percentage-closer filtering
///        (VASL-MODEL §5). Computed once per source at ingest; reweighting never runs it.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <limits>
#include <optional>
#include <vector>

#include "lattice/geometry/equirect.h"
#include "lattice/geometry/footprint.h"
#include "lattice/geometry/pose.h"
#include "lattice/memory/buffer_pool.h"
#include "lattice/records/records.h"
#include "lattice/tiles/tiling.h"

namespace vasl::ingest {

/// §5 τ: depth tolerance of the visibility test, 1.5 h (choice).
inline double DepthToleranceM(double vossel_size_m) { return 1.5 * vossel_size_m; }

/// §5 (choice): the slope-scaled tolerance of the visibility test, τ_k = τ + r·Δ·tanθ with cosθ
/// floored at kCosIncidenceMin: across one pixel of pitch Δ the range of a surface at incidence
/// θ changes by about r·Δ·tanθ, and without it a surface seen at grazing incidence would shadow
/// itself between pixel centres. `cos_inc` = |n·v|.
inline double SlopeScaledToleranceM(double tau_m, double range_m, double pixel_rad, double cos_inc) {
  // At most 1: |n·v| of a unit normal in float may round past it, and √(1 − c²) is then NaN.
  const double c = std::clamp(cos_inc, geometry::kCosIncidenceMin, 1.0);
  return tau_m + range_m * pixel_rad * std::sqrt(1.0 - c * c) / c;
}

/// §5: the tolerance of ComputeVisibility's tests of a vossel `to_sensor` (non-zero) from the
/// sensor whose record frame has normal `normal` (zero: none, taken as facing the sensor);
/// `pixel_rad` as SlopeScaledToleranceM's. The one computation ComputeVisibility and the
/// bounds on its tests (a revisit's scope) share.
inline double VosselToleranceM(double tau_m, const Eigen::Vector3d& to_sensor,
                               const Eigen::Vector3d& normal, double pixel_rad) {
  const Eigen::Vector3d n = normal.squaredNorm() < 0.5 ? to_sensor.normalized() : normal;
  const double range_m = to_sensor.norm();
  return SlopeScaledToleranceM(tau_m, range_m, pixel_rad, std::abs(n.dot(to_sensor)) / range_m);
}

/// §5: ComputeVisibility's test samples lie within kSamplePatchM·h of the vossel's frame
/// centroid (its 4×4 grid's corners at 0.375·√2·h = 0.53·h, rounded up).
inline constexpr double kSamplePatchM = 0.55;

/// The directions (a cap, world frame) in which ComputeVisibility's tests of the vossel whose
/// frame centroid is `x` read a panorama from a sensor at `o`: about x, of the angle its sample
/// patch subtends, one pixel (`pitch_rad`) wider for rounding. Its far side lies kSamplePatchM·h
/// beyond x. nullopt when the sensor lies within twice the patch of x (a test may read anywhere).
std::optional<tiles::ViewCap> SampleCap(const Eigen::Vector3d& x, const Eigen::Vector3d& o,
                                        double vossel_size_m, double pitch_rad);

/// Per pixel, the nearest range (metres) of occupied geometry from one source; +inf: none.
struct DepthPanorama {
  geometry::Pose pose;          ///< T_world_sensor of the source
  geometry::EquirectSize size;  ///< raster size (independent of the source image's size)
  std::vector<float> depth_m;   ///< row-major, row 0 up
  /// Rows [splat_row_begin, splat_row_end) hold every pixel that is not +inf (a bound: some
  /// may hold none); RenderDepthPanorama's are the rows its splats reached (empty: none).
  int splat_row_begin = 0, splat_row_end = std::numeric_limits<int>::max();

  float At(int i, int j) const { return depth_m[size_t(j) * size.width_px + i]; }

  DepthPanorama() = default;
  DepthPanorama(const DepthPanorama&) = default;
  DepthPanorama(DepthPanorama&&) = default;
  DepthPanorama& operator=(const DepthPanorama&) = default;
  DepthPanorama& operator=(DepthPanorama&&) = default;
  /// The depths' storage goes back to memory::GiveFloats: the next panorama of the size,
  /// taken by RenderDepthPanorama, reuses it without page faults.
  ~DepthPanorama() { memory::GiveFloats(std::move(depth_m)); }
};

/// Equirect raster size for a depth panorama whose pixel pitch is about `pitch_rad` (within
/// half a reach cell), capped to `max_width_px` columns: whole reach cells (tiles::
/// kReachBlockPx pixels) along both axes, so that a source's reach raster lines up with it.
geometry::EquirectSize DepthPanoramaSize(double pitch_rad, int max_width_px = 4096);

/// §5: the depth panorama of a source rendered from the lattice by splatting each vossel's
/// bounding sphere (radius h√3/2), dilated by the occluder's own footprint σ(r) at its range
/// (radius h√3/2 + σ(r), §3). Inside the splat the depth is the range at which the pixel's ray
/// crosses the vossel's plane (its record frame's centroid and normal, records::VosselFrame),
/// and only rays crossing it within that radius of the centroid are splatted (a surfel splat,
/// choice): a surface then does not shadow itself at grazing incidence. The paper uses the
/// measured range image for LiDAR; the splatted lattice is used for every source here
/// (choice): it has no holes between returns and equals the range image where returns exist,
/// and a new object in front of an older LiDAR's records shadows them. Parallel (TBB): splats
/// are binned by bands of rows, each band splatted by one task; of a large set of vossels,
/// blocks of neighbours are splatted nearest first, and a block lying behind the farthest
/// depth splatted so far in every reach cell it can fall in is left out (the same panorama:
/// its splats would lie behind the final depth everywhere).
/// With `splat_only` (a flag per vossel) only the flagged vossels are splatted: the panorama is
/// then exact wherever every vossel whose splat can fall is flagged (a revisit's cone).
/// With `cells` (a flag per reach cell, tiles::kReachBlockPx² pixels, row-major over the
/// panorama's cells; `size` whole cells, as DepthPanoramaSize gives) only the pixels of flagged
/// cells are splatted; the others stay +inf (a revisit reads no other). Its cost then follows
/// the flagged cells, not the panorama: blocks whose splats cannot fall in a flagged cell are
/// passed over whole, and the culling passes read the flagged cells alone.
/// RenderDepthPanorama culls front to back from this many splatted vossels (below, the passes
/// would cost more than they save).
inline constexpr size_t kCullMinVossels = 16384;
DepthPanorama RenderDepthPanorama(const records::VosselGeometry& geometry,
                                  const geometry::Pose& T_world_sensor,
                                  const geometry::EquirectSize& size, double divergence_rad,
                                  const std::vector<uint8_t>* splat_only = nullptr,
                                  const std::vector<uint8_t>* cells = nullptr);

/// Min-filters a depth panorama over a (2·radius_px+1)² window, columns wrapping at the seam:
/// every occluder grows by `radius_px` pixels. Used for cameras, whose samples read a
/// neighbourhood of pixels (bilinear read, pixel integration): a vossel is lit only where that
/// whole neighbourhood sees it (choice, the "dilation-aware" mask of §5 applied to the
/// sampling kernel).
/// With a row range [row_begin, row_end) only those rows are filtered (the rows a revisit's
/// visibility tests read); the others keep their depth, an upper bound of the filtered one.
void DilateDepthPanorama(DepthPanorama& depth, int radius_px, int row_begin = 0,
                         int row_end = -1);

/// Sets the depth to 0 (nothing reachable) at every pixel whose direction lies more than
/// `half_angle_rad` from `axis` (sensor frame): for a source that records nothing there, so
/// that its reach raster (tiles::ReachFromDepth) holds no change there as one it can see.
/// Call it after the visibility tests have read the panorama.
void MaskOutsideCone(DepthPanorama& depth, const Eigen::Vector3d& axis, double half_angle_rad);

/// §5: V_{k,m} for every vossel: the share of 17 points (a 4×4 grid and the centre; V is a
/// multiple of 1/17, stored exactly by the record's 8-bit codec) over the vossel's surface
/// patch (side h, in the plane (x_k, n_k) of its record frame) whose pixel in `depth` satisfies
/// D(p) ≥ r_p − τ_k (percentage-closer filtering over the vossel's projected footprint), with
/// the slope-scaled tolerance τ_k = τ + r·Δ·tanθ (choice: Δ the depth panorama's pixel pitch,
/// cosθ floored at kCosIncidenceMin), the range change of the surface across one pixel.
/// V = 1 lit, 0 < V < 1 penumbra, V = 0 shadow. With `only` (a flag per vossel) the other
/// vossels get V = 0 without being tested. `slope_pixels`: how many pixels apart the depth a
/// test reads may lie from its own pixel: 1, or 1 + the radius of DilateDepthPanorama when
/// `depth` was dilated (its min filter reads the surface itself up to that many pixels away, where
/// a surface at grazing incidence is nearer by r·Δ·tanθ per pixel: without it such a surface
/// shadows itself). Parallel (TBB). When at least kShadowByCellsMinVossels vossels are tested
/// on a panorama of whole reach cells, a vossel whose patch lies, beyond its tolerance, behind
/// the farthest depth of every reach cell it can fall in gets V = 0 without a test per sample
/// (exact: each of its tests would fail), and so do whole runs of consecutive vossels whose
/// box lies so behind them. `shadow_by_cells` false skips that pass: for a
/// panorama of a few splats, +inf in nearly every cell, it would shadow nothing.
inline constexpr size_t kShadowByCellsMinVossels = 4096;
std::vector<float> ComputeVisibility(const records::VosselGeometry& geometry,
                                     const DepthPanorama& depth, double tau_m,
                                     const std::vector<uint8_t>* only = nullptr,
                                     int slope_pixels = 1, bool shadow_by_cells = true);

}  // namespace vasl::ingest

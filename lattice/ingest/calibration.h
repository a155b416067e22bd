/// @file calibration.h
/// @brief Calibration health (VASL-MODEL §2.3): how well a scan's camera sits on its pose,
///        judged against the scan's own LiDAR before the camera's colours are fused.
/// @details For one (LiDAR, camera) pair, in the frame their poses share:
///          1. Every return x the camera sees is projected, (u, v) = π_c(x), and splatted into
///             analysis cells of s × s camera pixels, nearest return per cell, s the smallest
///             power of two at which the returns fill the image (of the cells within one of a
///             return, 90 % hold one): the check resolves what the LiDAR samples, no finer.
///          2. Round trip: (u, v) is lifted back with the measured range r = |x − o_c|,
///             x' = o_c + r·π_c⁻¹(u, v); |x − x'| tests the projection model itself (the
///             pinhole's iterative undistortion most of all), on an even sample of 100,000.
///          3. The LiDAR image: each return's intensity (or, without intensity, its colour's
///             Rec.709 luminance) spread bilinearly onto the four cell centres around it, into
///             cells whose nearest return lies within 5 % of its range; beside it the camera
///             image's luminance averaged over each cell.
///          4. Textured LiDAR patches (15 × 15 cells; the structure tensor's smaller eigenvalue
///             at least a tenth of the larger; no range step over 10 % inside; at most 600,
///             strongest first, none within 7 cells of another).
///          5. Each is searched for in the camera image by normalised cross-correlation
///             (invariant to the gain and offset between a LiDAR's reflectance and a camera's
///             luminance) within ±8 cells, and kept when the peak reaches 0.6, falls by 0.005 a
///             cell away on both axes (an edge or a smooth ramp does not locate), refines to a
///             subpixel peak by parabolas, searches back from the camera patch to the LiDAR
///             patch (within a cell), and agrees within a cell with the median shift of its 6
///             nearest matches (a miscalibration shifts an image smoothly; a look-alike patch
///             does not). The pixel residual of a match is |m − (u, v)|, camera pixels; the
///             offset |x − x''|, x'' = o_c + r·π_c⁻¹(m), says what it means on the surface.
///          6. The rotation that best takes the projections' rays onto the matches' rays
///             (Kabsch) says what kind of error it is: a camera turned off its pose shows as
///             that turn.
///          A pair is flagged when at least 20 patches matched and the 95th percentile of the
///          pixel residual exceeds max(1.5 px, 0.75 cell); unchecked when fewer matched, the
///          camera sees no return, or the LiDAR has neither intensity nor colour.
#pragma once

#include <cstddef>
#include <vector>

#include "lattice/ingest/sources.h"
#include "lattice/records/calibration.h"

namespace vasl::ingest {

/// The check's settings; the defaults are the ones documented above.
struct CalibrationSettings {
  int patch_radius = 7;          ///< template half-size, analysis cells
  int search_radius = 8;         ///< search window half-size, analysis cells
  double min_ncc = 0.6;          ///< least correlation of a match
  int min_matches = 20;          ///< fewer matches: unchecked
  double flag_p95_px = 1.5;      ///< flagged above this p95 pixel residual (or 0.75 cell)
  int max_features = 600;        ///< patches tried at most
  int max_analysis_width = 4096; ///< analysis cells across the image at most
};

/// §2.3 for one (LiDAR, camera) pair; `image` is the camera's decoded image. Never fails: what
/// it cannot judge it reports as unchecked, with the reason in `note`.
records::CalibrationHealth CheckCalibration(const LidarSource& lidar, const CameraSource& camera,
                                            const LinearImage& image,
                                            const CalibrationSettings& settings = {});

namespace internal {

/// The normalised cross-correlation of a (2R+1)² template (row-major, NaN where empty) against
/// a (2(R+S)+1)² window at each of its (2S+1)² shifts (row-major, dy then dx): over the cells
/// where both are finite, -inf where fewer than `min_n` pair or either side is flat. Each
/// shift's sums are taken in the template's row-major order (the same bits as one shift at a
/// time); CheckCalibration's patch search.
std::vector<double> CorrelationGrid(const std::vector<float>& templ,
                                    const std::vector<float>& window, int R, int S,
                                    size_t min_n);

}  // namespace internal

}  // namespace vasl::ingest

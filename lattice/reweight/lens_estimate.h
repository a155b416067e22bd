/// @file lens_estimate.h
/// @brief Lens dirt and fog from a rig's sequence (VASL-MODEL §9): the persistent
///        multiplicative map D < 1 and additive veil v > 0 of one camera, found from the
///        records of its frames against the colour the other records give their vossels.
/// @details Every record of the camera's sources (RGB, weight > 0 under the base profile) whose
///          vossel has other records of weight > 0 is a sample: its value y (a_{m,c} applied)
///          at pixel uv, and the reference x = Σ w C / Σ w over the vossel's other RGB records,
///          the fused colour without the record itself (leave one out, so that a dirty record
///          does not pull its own reference). The model of fusion/lens.h is
///          ```
///          y = g_m · (D(p) · x + v(p))
///          ```
///          1. g_m per source and channel: the median of y / (D·x + v) over its samples (gain
///             normalisation, so that one frame's exposure is not taken for dirt).
///          2. Per cell of a grid over the image, on the sum of the channels of y / g_m and x
///             (so that noise in one channel makes no dirt of its own): samples beyond 3.5
///             robust deviations of a least-squares line are dropped, twice; then dirt alone
///             (y/g = D·x) counts when 1 − D exceeds `min_dirt` and three standard errors, a
///             veil alone (y/g = x + v) when v exceeds `min_veil` per channel and three
///             standard errors, and both when one of them counts and the joint fit clears both
///             bounds. Either moves the cell's mean: a loss of contrast that keeps it (blur, a
///             footprint the other frames see otherwise) is neither. A cell with nothing found,
///             or fewer than `min_samples` samples, keeps D = 1, v = 0 exactly, so a clean
///             camera's map is all ones. Each channel then fits the model chosen (dirt may be
///             coloured).
///          3. Rounds: the next round corrects every sample's reference with the map found, so
///             that dirt on the other frames' pixels does not bias it, and fits again.
///          Residuals are taken in log space for the figures (log y − log g(Dx + v)).
///
///          Cost: `rounds` passes over the records (parallel over vossels), a parallel sort
///          of the samples by cell and a parallel fit per cell over each cell's contiguous
///          samples. Memory: 40 bytes per sample (the frames' records with a reference), and
///          one thread's part of them again while the parts are joined; no per-cell lists.
#pragma once

#include <cstdint>
#include <vector>

#include "absl/status/statusor.h"
#include "lattice/fusion/lens.h"
#include "lattice/fusion/profile.h"
#include "lattice/records/records.h"

namespace vasl::reweight {

/// One frame of the camera: its source id and image size.
struct LensFrame {
  int32_t source = 0;
  int width_px = 0;
  int height_px = 0;
};

struct LensOptions {
  int cell_px = 0;                 ///< grid cell edge, pixels; 0: chosen from the samples
  int samples_per_cell = 150;      ///< the automatic cell holds about this many samples
  int min_samples = 40;            ///< a cell with fewer keeps D = 1, v = 0
  double min_dirt = 0.08;          ///< dirt: D below 1 − min_dirt
  double min_veil = 0.02;          ///< veil: v above this, linear record units
  int rounds = 3;                  ///< fit, then refits with references corrected
};

struct LensEstimate {
  fusion::LensMap map;             ///< rig, camera, period left for the caller
  int64_t samples = 0;             ///< records that had a reference
  int64_t cells = 0;               ///< cells of the grid
  int64_t cells_fitted = 0;        ///< cells with at least min_samples samples
  int64_t cells_dirt = 0;          ///< cells with D < 1 in some channel
  int64_t cells_veil = 0;          ///< cells with v > 0 in some channel
  double cell_px = 0.0;            ///< the grid cell edge used
  double residual_before = 0.0;    ///< RMS log residual, D = 1, v = 0, gains 1
  double residual_after = 0.0;     ///< RMS log residual under the map and gains
};

/// Estimates the lens map of the camera whose frames are `frames` (all of one image size, at
/// least two) from `records` (sorted by vossel) weighed under `base`, which must not apply a
/// lens map to those frames. INVALID_ARGUMENT for frames that disagree in size or options out
/// of range; FAILED_PRECONDITION when no record of the frames shares a vossel with another.
absl::StatusOr<LensEstimate> EstimateLensMap(const records::RecordSet& records,
                                             size_t vossel_count, double vossel_size_m,
                                             const fusion::WeightingProfile& base,
                                             const std::vector<LensFrame>& frames,
                                             const LensOptions& options = {});

}  // namespace vasl::reweight

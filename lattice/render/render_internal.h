/// @file render_internal.h
/// @brief Internals of the §8 renderer exposed for tests: the crack-closing cell margin as a
///        parameter, so that a test can show why the default was chosen.
#pragma once

#include "absl/status/statusor.h"
#include "lattice/records/records.h"
#include "lattice/render/render.h"

namespace vasl::render::internal {

/// Default expansion of a vossel's cell, in vossel units (index space), inside which a ray's
/// intersection with the vossel's plane is accepted (VASL-MODEL §8, *(choice)*).
/// @details The plane (x_k, n_k) of a curved surface departs from the surface by ~δ²/(2R) at a
///          lateral distance δ from x_k, so near a cell face a ray that enters cell k can cross
///          k's plane just beyond the face while crossing the neighbour's plane just before it:
///          both tests fail and the pixel leaks through (a crack). Accepting hits up to a
///          quarter vossel outside the cell closes those cracks (render_test
///          `MarginClosesCracks`, h = 0.05 m, 2048×1024: with no margin 8416 of 2097152 pixels
///          leak from inside a sphere of R = 20h and 10 of 24688 on a convex sphere of R = 5h;
///          with 0.25 h none leak) while keeping any
///          accepted point within 0.25·h of the vossel that owns it, far below the 1-vossel
///          resolution of the lattice itself.
inline constexpr double kDefaultCellMarginVox = 0.25;

/// RenderEquirect (§8) with an explicit cell margin, vossel units (≥ 0); with
/// `skip_to_near_ranges` false every ray marches from the eye (or its start range), without the
/// per-block skip of the empty space before the nearest leaf (render.cc NearRanges), so that a
/// test can show the skip changes no pixel.
absl::StatusOr<RenderImage> RenderEquirectWithMargin(const records::VosselGeometry& geometry,
                                                     const records::FusedValues& fused,
                                                     const RenderRequest& request,
                                                     double cell_margin_vox,
                                                     const ViewBlendInputs* blend = nullptr,
                                                     bool skip_to_near_ranges = true);

}  // namespace vasl::render::internal

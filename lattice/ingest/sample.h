/// @file sample.h
/// @brief Observation records of one source (VASL-MODEL §3, §4, §6): range, incidence,
///        footprint, pixel coordinates, visibility and the sample itself.
#pragma once

#include <vector>

#include "lattice/ingest/sources.h"
#include "lattice/ingest/visibility.h"
#include "lattice/records/records.h"

namespace vasl::ingest {

/// Records of one equirect camera: one per vossel with V > 0. The sample is the §4.1 matched
/// filter when the pixel footprint is sharper than s* = h/2 (an elliptical Gaussian in the
/// tangent plane, σ_K² = s*² − s² per axis, evaluated by 3×3 Gauss–Hermite quadrature whose
/// points are projected into the image and read bilinearly with seam wrap; weights sum to 1),
/// else a bilinear point sample (the §4.2 range weight K_range discounts it at fusion).
/// conf[saturation] = 1 − the kernel's weight on clipped pixels (§9); other factors 1.
records::RecordSet SampleCamera(const records::VosselGeometry& geometry, const CameraSource& camera,
                                const std::vector<float>& vis);

/// Records of one LiDAR: one per vossel that holds returns of this LiDAR and has V > 0; the
/// sample is the mean intensity of those returns (1 when the scan has no intensity).
/// Footprint from the beam divergence (§3).
records::RecordSet SampleLidar(const records::VosselGeometry& geometry, const LidarSource& lidar,
                               const DepthPanorama& depth, const std::vector<float>& vis);

/// Every stage for every source: depth panorama → visibility → records, merged and sorted by
/// vossel. Cameras with an empty image are decoded through their `load` one at a time.
/// `on_source(done, total)` reports progress after each source (may be empty). Fails only when
/// a camera's image cannot be loaded.
absl::StatusOr<records::RecordSet> BuildRecords(const records::VosselGeometry& geometry,
                                                const SourceSet& sources,
                                                const std::function<void(size_t, size_t)>& on_source);

}  // namespace vasl::ingest

/// @file sample.h
/// @brief Observation records of one source (VASL-MODEL §3, §4, §6): range, incidence,
///        footprint, pixel coordinates, visibility and the sample itself.
#pragma once

#include <optional>
#include <utility>
#include <vector>

#include "lattice/geometry/footprint.h"
#include "lattice/geometry/image_projection.h"
#include "lattice/ingest/artefacts.h"
#include "lattice/ingest/sources.h"
#include "lattice/ingest/visibility.h"
#include "lattice/records/records.h"
#include "lattice/tiles/tiling.h"

namespace vasl::ingest {

/// A camera's image projection (geometry/image_projection.h), for an image of the given size.
using geometry::ImageProjection;
ImageProjection ProjectionOf(const CameraSource& camera, int width_px, int height_px);


/// The rows [begin, end) of `camera`'s image that SampleCamera reads for the vossels with
/// vis > 0 (every kernel point's bilinear read): all of a pinhole photo's. A correction of the
/// image (the channels' fringing, §9) need touch no other row.
std::pair<int, int> SampledRows(const records::VosselGeometry& geometry,
                                const CameraSource& camera, const std::vector<float>& vis);

/// Records of one camera: one per vossel with V > 0 (that a pinhole image holds). The sample is the §4.1 matched
/// filter when the pixel footprint is sharper than s* = h/2 (an elliptical Gaussian in the
/// tangent plane, σ_K² = s*² − s² per axis, evaluated by 3×3 Gauss–Hermite quadrature whose
/// points are projected into the image and read bilinearly with seam wrap; weights sum to 1),
/// else a bilinear point sample (the §4.2 range weight K_range discounts it at fusion).
/// §9 from `artefacts` (DetectArtefacts of the camera's image): conf[saturation] is the
/// kernel's weighted read of the saturation map, conf[flare] that of the flare map over the
/// kernel's points on valid pixels; points on invalid pixels (flare map < kFlareInvalidBelow)
/// give no colour, and a record with less than half its kernel's weight on valid pixels (a
/// point sample on an invalid one) is flagged kFlagInvalidated; conf[codec] and conf[smear]
/// are the kernel's reads of the codec and smear maps; conf[dirt] and conf[fog] are 1 (a lens
/// map lowers them at fusion). An image with alpha (LinearImage::alpha) counts each point by
/// its coverage: the sample is the colour of the covered part, and a record whose kernel (or
/// point sample) is covered less than geometry::kCoveredAtLeast is flagged kFlagInvalidated, as a
/// flare-invalid one is (decision: a transparent pixel is one the camera does not report).
records::RecordSet SampleCamera(const records::VosselGeometry& geometry, const CameraSource& camera,
                                const std::vector<float>& vis, const ArtefactMaps& artefacts);

/// Records of one LiDAR: one per vossel that holds returns of this LiDAR and has V > 0; the
/// sample is the mean intensity of those returns (1 when the scan has no intensity).
/// Footprint from the beam divergence (§3).
records::RecordSet SampleLidar(const records::VosselGeometry& geometry, const LidarSource& lidar,
                               const DepthPanorama& depth, const std::vector<float>& vis);

/// Records of the colour of one LiDAR's returns (lidar.rgb, source lidar.colour_id, modality
/// RGB): one per vossel that holds returns of this LiDAR and has V > 0, the sample the mean
/// colour of those returns, seen from the scanner's origin with the LiDAR's footprint (§3) and
/// visibility (§5). conf[saturation] = 1 − the share of those returns with a channel at the
/// clip level (1, the largest code of an integer colour).
records::RecordSet SamplePointColour(const records::VosselGeometry& geometry,
                                     const LidarSource& lidar, const DepthPanorama& depth,
                                     const std::vector<float>& vis);

/// What one source contributes to a version: its records and its reach raster (the depth
/// panorama its visibility read, coarsened: tiles::ReachFromDepth).
struct SourceRecords {
  records::RecordSet records;
  tiles::ReachRaster reach;
};

/// Angular sampling of a source's depth panorama (radians per pixel): a LiDAR's from its point
/// count (its returns spread over the sphere, W·H ≈ 2·H² ≈ points), a camera's its
/// ImageProjection::PitchRad. Fixed per source, so a revisit sees the same raster.
double LidarDepthPitchRad(size_t point_count);
/// Pixels by which a camera's depth panorama is dilated (see DilateDepthPanorama).
int CameraSampleRadiusPx();

/// How a source's §5 visibility tests read its depth panorama: the raster, the splats' growth,
/// the pixels of the slope-scaled tolerance and of a camera's dilation. The records
/// (LidarRecords, CameraRecords) and an ingest's check of which tests a change can alter read
/// it from here, so both see the same tests.
struct DepthView {
  geometry::EquirectSize size;  ///< the depth panorama's raster (DepthPanoramaSize)
  double divergence_rad = 0.0;  ///< RenderDepthPanorama's splat growth
  int slope_pixels = 1;         ///< ComputeVisibility's slope_pixels
  int dilate_px = 0;            ///< DilateDepthPanorama's radius (0: none)
};
/// A LiDAR's (or its point colour's) view from its point count and beam divergence.
DepthView LidarDepthView(size_t point_count, double divergence_rad);
/// A camera's view of a width_px × height_px image (its image need not be decoded).
DepthView CameraDepthView(const CameraSource& camera, int width_px, int height_px);

/// §5 for one source, before any of its points or pixels is read: its depth panorama of the
/// geometry (splatting the `context` vossels; all without), the visibility V of the vossels its
/// records can be made for (`only`, all without; of a pinhole camera those its image holds;
/// 0 elsewhere), and its reach raster. LidarVisibility / CameraVisibility then the records'
/// sampling are what LidarRecords / CameraRecords do.
/// With `read_cells` (a revisit's: per reach cell of the panorama, nonzero where the tests of
/// `only` read) the panorama is splatted only on those cells; elsewhere it and the reach raster
/// say +inf, a bound the caller must not use (tiles::MergeReach keeps the old one there).
struct SourceVisibility {
  DepthPanorama depth;       ///< as the tests read it (a camera's dilated on the rows they read)
  std::vector<float> vis;    ///< V per vossel
  tiles::ReachRaster reach;  ///< of the depth (a pinhole camera's 0 beyond its field)
  int image_w = 0, image_h = 0;  ///< a camera's: the image size it was found for
};
SourceVisibility LidarVisibility(const records::VosselGeometry& geometry,
                                 const geometry::Pose& pose, const DepthView& view,
                                 const std::vector<uint8_t>* only = nullptr,
                                 const std::vector<uint8_t>* context = nullptr,
                                 const std::vector<uint8_t>* read_cells = nullptr);
/// A camera's, for an image of width_px × height_px (its image need not be decoded).
SourceVisibility CameraVisibility(const records::VosselGeometry& geometry,
                                  const CameraSource& camera, int width_px, int height_px,
                                  const std::vector<uint8_t>* only = nullptr,
                                  const std::vector<uint8_t>* context = nullptr,
                                  const std::vector<uint8_t>* read_cells = nullptr);

/// The geometric terms of a record of returns on vossel k (§3, on its record frame), as
/// SampleLidar makes them; false when k's frame lies at the sensor (no record).
struct ReturnTerms {
  double range_m = 0.0, cos_inc = 0.0;
  geometry::SurfaceFootprint foot;
  Eigen::Vector2d uv = Eigen::Vector2d::Zero();  ///< on the depth panorama's raster
};
bool ReturnTermsOf(const records::VosselGeometry& geometry, size_t k, const geometry::Pose& pose,
                   double divergence_rad, const geometry::EquirectSize& size, ReturnTerms* out);

/// §5 then §3-§6 for one LiDAR: depth panorama of `geometry` from the LiDAR, visibility,
/// records. With `only` (a flag per vossel) records are made for the flagged vossels alone;
/// with `context` the depth panorama splats only the flagged vossels (it must flag every vossel
/// that can occlude an `only` vossel; the reach raster is then exact only where it does).
SourceRecords LidarRecords(const records::VosselGeometry& geometry, const LidarSource& lidar,
                           const std::vector<uint8_t>* only = nullptr,
                           const std::vector<uint8_t>* context = nullptr);

/// The same for the colour source of a LiDAR with per-point colour (SamplePointColour).
SourceRecords PointColourRecords(const records::VosselGeometry& geometry, const LidarSource& lidar,
                                 const std::vector<uint8_t>* only = nullptr,
                                 const std::vector<uint8_t>* context = nullptr);

/// The same for one camera; its image is decoded through `load` when `image` is empty (and
/// freed afterwards). Fails only when the image cannot be loaded.
absl::StatusOr<SourceRecords> CameraRecords(const records::VosselGeometry& geometry,
                                            const CameraSource& camera,
                                            const std::vector<uint8_t>* only = nullptr,
                                            const std::vector<uint8_t>* context = nullptr);

/// The records of a source whose visibility is known (LidarVisibility, CameraVisibility on the
/// same geometry and source): the sampling alone. A camera's image must have the size its
/// visibility was found for (FAILED_PRECONDITION otherwise).
SourceRecords LidarRecords(const records::VosselGeometry& geometry, const LidarSource& lidar,
                           SourceVisibility visibility);
SourceRecords PointColourRecords(const records::VosselGeometry& geometry, const LidarSource& lidar,
                                 SourceVisibility visibility);
absl::StatusOr<SourceRecords> CameraRecords(const records::VosselGeometry& geometry,
                                            const CameraSource& camera,
                                            SourceVisibility visibility);

}  // namespace vasl::ingest

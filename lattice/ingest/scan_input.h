/// @file scan_input.h
/// @brief What a capture rig sends for one scan: LiDAR points, pose, sensor model, panoramas.
#pragma once

#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "lattice/geometry/pinhole.h"
#include "lattice/geometry/pose.h"
#include "lattice/records/records.h"

namespace vasl::ingest {

/// LiDAR part of a scan: points in the sensor frame.
struct LidarData {
  std::vector<float> xyz_sensor_m;  ///< 3 floats per point, sensor frame, metres
  std::vector<float> intensity;     ///< empty, or one per point (linear, any scale)
  std::vector<float> rgb;           ///< empty, or 3 per point: the point's colour, linear
  double divergence_rad = 0.3e-3;   ///< full beam divergence θ_div (§3)
  /// The scan's range grid (LidarSource::grid_cell): rows × columns, and per point its cell
  /// row·columns + column; empty: an unordered scan.
  int32_t grid_rows = 0, grid_columns = 0;
  std::vector<uint32_t> grid_cell;
};

/// An equirectangular panorama that spans part of the sphere (a camera without a nadir, an E57
/// spherical image of less than 360° × 180°): the size of the whole sphere's panorama at the
/// image's pixel pitch, twice as wide as high, and where the image's top-left pixel lies in it.
/// The rest of the sphere is uncovered (ingest::PlaceInSphere).
struct SphereWindow {
  int width_px = 0, height_px = 0;
  int left_px = 0, top_px = 0;
};

/// A cylindrical panorama (an E57 cylindricalRepresentation): columns every `pixel_width_rad`
/// of azimuth, centred on the camera's x axis as an equirect panorama's are (§2.1); rows every
/// `pixel_height_m` up a cylinder of `radius_m` around the camera's z axis, the horizon (z = 0)
/// at row coordinate `principal_y_px` (pixel i spans [i, i + 1)), so row coordinate v looks at
/// elevation atan((principal_y_px − v)·pixel_height_m / radius_m). Resampled at decode into the
/// equirect part of the sphere it covers (ingest::CylinderToSphere).
struct CylinderImage {
  double pixel_width_rad = 0.0;
  double pixel_height_m = 0.0;
  double radius_m = 0.0;
  double principal_y_px = 0.0;
};

/// One image of a scan with its own pose: an equirectangular panorama (§2.1) or, with
/// `pinhole`, a pinhole photo (§2.2).
struct PanoramaData {
  std::string name;                 ///< unique within the scan, e.g. "cam0"
  geometry::Pose pose;              ///< T_world_camera; the panorama's sensor frame (§2.1)
  records::Modality modality = records::Modality::kRgb;  ///< kRgb or kIr
  std::string encoded_image;        ///< PNG, JPEG, EXR or TIFF bytes (OpenImageIO decodes)
  /// Empty, or the image's mask: PNG, JPEG, EXR or TIFF bytes of the image's own size whose
  /// first channel, over its largest value, is the share of each pixel the camera reports (0
  /// where a tripod, rig or operator is masked out), combined with the image's alpha
  /// (ingest::ApplyMask). Ignored for a visual reference.
  std::string encoded_mask;
  double angular_resolution_rad = 0.0;  ///< 0: from the image size (§3 θ_pix)
  /// Set: a pinhole photo with these intrinsics (their width and height are ignored: the
  /// image's own size counts); unset: an equirectangular panorama.
  std::optional<geometry::PinholeIntrinsics> pinhole;
  /// Set: an equirect panorama of part of the sphere, placed there as decoded; unset: the
  /// image is the whole sphere. Not for a pinhole photo; ignored for a visual reference.
  std::optional<SphereWindow> sphere;
  /// Set: a cylindrical panorama, resampled into its part of the sphere as decoded. Neither
  /// with `pinhole` nor with `sphere`; ignored for a visual reference.
  std::optional<CylinderImage> cylinder;
  /// True: a visual reference, a photo kept with the scan as a blob (provenance) for people to
  /// look at; no projection, no source, no records. Its modality, angular resolution and
  /// pinhole are ignored.
  bool visual_reference = false;
};

/// One scan as sent by a capture rig.
struct ScanInput {
  std::string scan_name;            ///< client's scan id, unique in the project
  std::string rig;                  ///< rig / device name (provenance)
  std::string captured_utc;         ///< capture time, ISO 8601 (may be empty)
  geometry::Pose pose;              ///< T_world_scanner of the LiDAR (of the rig when camera-only)
  /// The scan's returns; no points: a camera-only scan, whose images colour the geometry the
  /// project already has.
  LidarData lidar;
  std::vector<PanoramaData> panoramas;
  /// The client's request id (empty: none): a retry under the id of a committed ingest is
  /// answered with that ingest's version instead of being ingested again.
  std::string request_id;
};

/// Progress of a long operation: stage name and fraction of the whole in [0, 1].
struct Progress {
  std::string stage;
  double fraction = 0.0;
};
/// Told as each stage of a long operation starts; its answer says whether the caller still
/// wants the work. OK goes on; any other status (CANCELLED when the caller went away,
/// DEADLINE_EXCEEDED when its deadline passed) stops the work there, before its commit, and
/// the operation fails with that status: nothing of it is kept and its memory is freed.
using ProgressFn = std::function<absl::Status(const Progress&)>;

}  // namespace vasl::ingest

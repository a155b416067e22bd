/// @file synthetic_scene.h
/// @brief A synthetic site with analytic ground truth: a textured room with one occluding box,
///        LiDAR scans and pixel-integrated equirectangular panoramas generated as a rig would.
/// @details The scene is the inside of an axis-aligned room (world frame of VASL-MODEL §2:
///          right-handed, z up, metres, floor at z = 0) plus one solid box standing on the
///          floor. Every surface is Lambertian with an analytic, smooth, per-face albedo; there
///          is no lighting (radiance = albedo, view-independent). Everything here is exact and
///          deterministic (seeded), so tests can compare what the store reconstructs with the
///          truth: ray hits (Intersect), visibility (Visible), colour (Albedo), range
///          (RenderPanorama depth) and shadow regions (FaceSamples).
///
///          Sensor frames follow §2.1: a LiDAR's rays and a panorama's pixels are both laid
///          out on the equirectangular grid of the sensor frame (EquirectUnproject gives the
///          direction of a continuous pixel coordinate).
/// @warning All functions are thread-safe (const, no shared mutable state).
#pragma once

#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "lattice/geometry/pose.h"
#include "lattice/ingest/scan_input.h"

namespace vasl::scenes {

/// Face ids returned by SyntheticRoom::Intersect. Room faces face inward, box faces outward.
inline constexpr int kFaceNone = -1;
inline constexpr int kFaceFloor = 0;      ///< room z = min
inline constexpr int kFaceCeiling = 1;    ///< room z = max
inline constexpr int kFaceWallXMin = 2;   ///< room x = min
inline constexpr int kFaceWallXMax = 3;   ///< room x = max
inline constexpr int kFaceWallYMin = 4;   ///< room y = min
inline constexpr int kFaceWallYMax = 5;   ///< room y = max: the wall the occluder shadows
inline constexpr int kFaceBoxXMin = 6;    ///< occluder x = min
inline constexpr int kFaceBoxXMax = 7;    ///< occluder x = max
inline constexpr int kFaceBoxYMin = 8;    ///< occluder y = min
inline constexpr int kFaceBoxYMax = 9;    ///< occluder y = max
inline constexpr int kFaceBoxTop = 10;    ///< occluder z = max
inline constexpr int kFaceBoxBottom = 11; ///< occluder z = min (rests on the floor; never seen)
inline constexpr int kFaceCount = 12;

/// Height of a rig's panoramic camera above its LiDAR, metres (+z world).
inline constexpr double kCameraAboveLidarM = 0.10;

/// An axis-aligned box in the world frame, metres.
struct Aabb {
  Eigen::Vector3d min_m = Eigen::Vector3d::Zero();  ///< lower corner, world, metres
  Eigen::Vector3d max_m = Eigen::Vector3d::Zero();  ///< upper corner, world, metres
};

/// The first surface a ray meets.
struct SceneHit {
  bool valid = false;                                   ///< false: nothing before t_max
  double t_m = 0.0;                                     ///< distance along the unit ray, metres
  Eigen::Vector3d x_world = Eigen::Vector3d::Zero();    ///< hit point, world, metres
  Eigen::Vector3d n_world = Eigen::Vector3d::Zero();    ///< unit normal facing the ray origin side
  int face = kFaceNone;                                 ///< kFace* id
  Eigen::Vector3f albedo_linear = Eigen::Vector3f::Zero();  ///< linear RGB in [0.05, 0.95]
  float reflectance = 0.0f;  ///< LiDAR reflectance = Rec.709 luminance of albedo_linear
};

/// The canonical synthetic site: a 6 m × 5 m × 3 m room with one 0.8 m × 0.8 m × 1.8 m box.
class SyntheticRoom {
 public:
  /// The canonical test scene (geometry, stations and novel views documented in the .cc).
  static SyntheticRoom Default();

  /// Interior of the room, world, metres.
  const Aabb& RoomBounds() const { return room_; }
  /// The solid occluding box standing on the floor, world, metres.
  const Aabb& OccluderBounds() const { return box_; }

  /// First hit of the ray o + t·d, 0 < t ≤ t_max_m. `d_unit` must be unit length. The origin
  /// is expected inside the room and outside the occluder (the box is then skipped).
  SceneHit Intersect(const Eigen::Vector3d& o_world, const Eigen::Vector3d& d_unit,
                     double t_max_m) const;

  /// Analytic visibility: true when the segment o → x meets no surface before x − eps_m
  /// (x itself may lie on a surface). False when x lies outside the room.
  bool Visible(const Eigen::Vector3d& o_world, const Eigen::Vector3d& x_world,
               double eps_m = 1e-6) const;

  /// Scanner (LiDAR) poses T_world_scanner: 4 stations 1.30–1.55 m above the floor, ≥ 1 m from
  /// the walls and the box, yawed. Station 0 sees the box in front of wall y = max (it casts a
  /// shadow there); station 1 sees that shadowed region lit.
  const std::vector<geometry::Pose>& Stations() const { return stations_; }

  /// Viewpoints for render tests: inside the room, at no station, not inside the box.
  const std::vector<geometry::Pose>& NovelViews() const { return novel_views_; }

  /// Linear RGB albedo of point x on face `face`, each channel in [0.05, 0.95]. Smooth: the
  /// finest feature (sinusoid wavelength, band edge width) is ≥ 0.3 m.
  Eigen::Vector3f Albedo(const Eigen::Vector3d& x_world, int face) const;

  /// Unit normal of a face, pointing into the free space of the room.
  static Eigen::Vector3d FaceNormal(int face);

  /// Points on `face` on a regular grid of pitch spacing_m, kept when they (and 8 neighbours
  /// at distance margin_m within the face plane) are visible from every origin in `lit_from`
  /// and hidden from every origin in `shadowed_from`. The face border (margin_m) is excluded.
  std::vector<Eigen::Vector3d> FaceSamples(int face, double spacing_m, double margin_m,
                                           const std::vector<Eigen::Vector3d>& lit_from,
                                           const std::vector<Eigen::Vector3d>& shadowed_from) const;

  /// Points of wall y = max shadowed by the occluder from station 0 (its LiDAR and its
  /// camera) and lit from station 1 (LiDAR and camera), 0.1 m grid, 0.15 m margin.
  std::vector<Eigen::Vector3d> ShadowSamples() const;

  /// Points of wall y = max lit from both stations 0 and 1 (LiDAR and camera), same grid: the
  /// control region for visibility tests.
  std::vector<Eigen::Vector3d> LitSamples() const;

 private:
  Aabb room_;
  Aabb box_;
  std::vector<geometry::Pose> stations_;
  std::vector<geometry::Pose> novel_views_;
};

/// The pose of a rig's panoramic camera at a station: kCameraAboveLidarM above the LiDAR
/// (+z world), same orientation.
geometry::Pose CameraPoseForStation(const geometry::Pose& T_world_scanner);

/// Rec.709 luminance of a linear RGB triple (the synthetic LiDAR's reflectance).
float Luminance(const Eigen::Vector3f& rgb_linear);

/// LiDAR settings. Rays lie on the centres of an azimuth_steps × elevation_steps equirect grid
/// of the sensor frame (§2.1); rays within 10° of the nadir are skipped (the tripod's blind
/// cone), the zenith is kept.
struct LidarSettings {
  int azimuth_steps = 1800;      ///< columns over 2π
  int elevation_steps = 900;     ///< rows over π
  double range_noise_m = 0.002;  ///< 1-σ Gaussian noise added to the range, metres
  double max_range_m = 50.0;     ///< no return beyond this range, metres
  double nadir_blind_rad = 10.0 * M_PI / 180.0;  ///< skipped cone half-angle around −z, rad
  uint64_t seed = 1;             ///< noise seed (results do not depend on thread count)
};

/// A LiDAR scan: points in the SENSOR frame, row-major over the ray grid (row 0 up).
struct LidarScan {
  std::vector<float> xyz_sensor_m;  ///< 3 floats per point, sensor frame, metres
  std::vector<float> intensity;     ///< 1 per point: reflectance in [0.05, 0.95]
};

/// Simulates a LiDAR at T_world_scanner: one return per ray, range = analytic range + noise.
LidarScan GenerateLidar(const SyntheticRoom& room, const geometry::Pose& T_world_scanner,
                        const LidarSettings& settings);

/// An equirectangular panorama (§2.1) with its ground-truth range.
struct Panorama {
  int width_px = 0;         ///< W
  int height_px = 0;        ///< H (row 0 looks up)
  std::vector<float> rgb;   ///< H·W·3 linear RGB, row-major
  std::vector<float> depth_m;  ///< H·W range of the pixel-centre ray, metres; +inf: no hit
};

/// Renders the panorama of a camera at T_world_camera: each pixel is the mean albedo over
/// supersample² stratified sub-pixel rays covering [i, i+1) × [j, j+1) (pixel integration, not
/// point sampling; supersample = 1 samples the centre only). Depth is the centre ray's range.
Panorama RenderPanorama(const SyntheticRoom& room, const geometry::Pose& T_world_camera,
                        int width_px, int height_px, int supersample = 4);

/// Linear → sRGB transfer (IEC 61966-2-1) and rounding to 8 bits, H·W·3 bytes: exactly the
/// pixel values EncodePng writes.
std::vector<uint8_t> ToSrgb8(const Panorama& pano);

/// Encodes the panorama's rgb as an 8-bit sRGB PNG (OpenImageIO, in memory).
absl::StatusOr<std::string> EncodePng(const Panorama& pano);

/// Writes a binary_little_endian PLY with `element vertex N` and float x, y, z, intensity.
absl::Status WritePly(const LidarScan& scan, const std::filesystem::path& path);

/// Writes a numpy .npy v1.0 file of little-endian float32 ('<f4'), C order, given shape.
absl::Status WriteNpy(const std::vector<float>& data, const std::vector<size_t>& shape,
                      const std::filesystem::path& path);

/// The scan of station `station` as a rig sends it, ready for Engine::IngestScan: LiDAR points
/// (seeded with lidar.seed) and the station camera's panorama (pano_width_px × pano_width_px/2,
/// pixel-integrated, encoded as PNG), named "scan-<station+1>" with one panorama "cam0".
absl::StatusOr<ingest::ScanInput> MakeScanInput(const SyntheticRoom& room, size_t station,
                                                const LidarSettings& lidar, int pano_width_px,
                                                int supersample = 4);

}  // namespace vasl::scenes

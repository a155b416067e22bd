/// @file synthetic_scene.h
/// @brief Synthetic sites with analytic ground truth, and the LiDAR scans and pixel-integrated
///        equirectangular panoramas a rig would record in them.
/// @details `Scene` is what the generators (GenerateLidar, RenderPanorama, MakeScanInput) need
///          of a site: an exact ray caster (Intersect), the site's free-space bounds, its
///          stations, novel viewpoints and per-face albedo; visibility (Visible) is defined once
///          from Intersect. Two sites implement it: `SyntheticRoom` (here: one room with one
///          box, optionally with extra boxes) and `CorridorSite` (corridor_site.h: a row of
///          rooms joined by doors).
///
///          SyntheticRoom is the inside of an axis-aligned room (world frame of VASL-MODEL §2:
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
#include "lattice/geometry/pinhole.h"
#include "lattice/geometry/pose.h"
#include "lattice/ingest/scan_input.h"
#include "lattice/ingest/sources.h"

namespace vasl::scenes {

/// Face ids returned by SyntheticRoom::Intersect. Room faces face inward, box faces outward.
/// Extra boxes (SyntheticRoom::WithExtraBox) number their faces from kFaceCount on, see
/// SyntheticRoom::ExtraBoxFace. kFaceNone (no hit) is shared by every Scene.
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

/// The six sides of a solid axis-aligned box, in the order every box's face ids are numbered
/// (SyntheticRoom's occluder: kFaceBoxXMin + side; extra boxes and CorridorSite solids: a
/// per-box first id + side). Box faces face outward.
inline constexpr int kBoxSideXMin = 0;    ///< x = min, normal −x
inline constexpr int kBoxSideXMax = 1;    ///< x = max, normal +x
inline constexpr int kBoxSideYMin = 2;    ///< y = min, normal −y
inline constexpr int kBoxSideYMax = 3;    ///< y = max, normal +y
inline constexpr int kBoxSideTop = 4;     ///< z = max, normal +z
inline constexpr int kBoxSideBottom = 5;  ///< z = min, normal −z
inline constexpr int kBoxSideCount = 6;
static_assert(kFaceBoxXMin + kBoxSideBottom == kFaceBoxBottom, "occluder faces follow the sides");

/// Height of a rig's panoramic camera above its LiDAR, metres (+z world).
inline constexpr double kCameraAboveLidarM = 0.10;

/// An axis-aligned box in the world frame, metres.
struct Aabb {
  Eigen::Vector3d min_m = Eigen::Vector3d::Zero();  ///< lower corner, world, metres
  Eigen::Vector3d max_m = Eigen::Vector3d::Zero();  ///< upper corner, world, metres
};

/// Axis (0 = x, 1 = y, 2 = z) a box side is normal to.
inline int BoxSideAxis(int side) { return side / 2; }
/// True for the sides at the box's max corner (x max, y max, top).
inline bool BoxSideAtMax(int side) {
  return side == kBoxSideXMax || side == kBoxSideYMax || side == kBoxSideTop;
}
/// Outward unit normal of a box side.
Eigen::Vector3d BoxSideNormal(int side);

/// Euclidean distance from a point to a box (0 inside or on it), metres.
double DistanceToAabb(const Eigen::Vector3d& x_world, const Aabb& box);

/// The interval of a ray's line inside a box (slab method).
struct SlabInterval {
  bool hit = false;      ///< false: the line misses the box (t_near_m > t_far_m, or parallel)
  double t_near_m = 0.0; ///< where the line enters the box (may be ≤ 0), metres along the ray
  double t_far_m = 0.0;  ///< where it leaves, metres along the ray
  int side_near = -1;    ///< kBoxSide* of the entry face (−1 if no slab bounds the entry)
};

/// The slab interval of the line o + t·d, t ∈ ℝ, and `box`: the intersection of the three
/// slabs' intervals. Exact for d[a] = 0 (inside the slab: no bound; outside: a miss). Monotone:
/// for a box containing another, the interval contains the other's (so it can cull rays).
SlabInterval RaySlabInterval(const Aabb& box, const Eigen::Vector3d& o_world,
                             const Eigen::Vector3d& d_unit);

/// Where a ray enters a solid box.
struct BoxEntry {
  bool valid = false;  ///< false: the ray misses the box, or starts inside or on it
  double t_m = 0.0;    ///< entry distance along the unit ray, metres (> 0 when valid)
  int side = -1;       ///< kBoxSide* of the entry face
};

/// Entry of the ray o + t·d into `box` (RaySlabInterval): valid when the slabs' entry t is
/// positive and ≤ their exit t. A ray starting inside the box (or on its surface, leaving it)
/// has no entry: solids are seen from outside only.
BoxEntry RayEntersBox(const Aabb& box, const Eigen::Vector3d& o_world,
                      const Eigen::Vector3d& d_unit);

/// The first surface a ray meets.
struct SceneHit {
  bool valid = false;                                   ///< false: nothing before t_max
  double t_m = 0.0;                                     ///< distance along the unit ray, metres
  Eigen::Vector3d x_world = Eigen::Vector3d::Zero();    ///< hit point, world, metres
  Eigen::Vector3d n_world = Eigen::Vector3d::Zero();    ///< unit normal facing the ray origin side
  int face = kFaceNone;  ///< the scene's face id (SyntheticRoom: kFace*), kFaceNone: no hit
  Eigen::Vector3f albedo_linear = Eigen::Vector3f::Zero();  ///< linear RGB in [0.05, 0.95]
  float reflectance = 0.0f;  ///< LiDAR reflectance = Rec.709 luminance of albedo_linear
};

/// A synthetic site with analytic ground truth: what the scan and panorama generators need.
/// Face ids are the implementation's (≥ 0; kFaceNone = −1 means no hit); Albedo takes the id
/// Intersect returned. Implementations are immutable after construction, so every method is
/// thread-safe.
class Scene {
 public:
  virtual ~Scene() = default;

  /// First hit of the ray o + t·d, 0 < t ≤ t_max_m; `d_unit` must be unit length, `o_world`
  /// inside the site's free space. Exact and deterministic; the hit point lies exactly on the
  /// plane of its face, the normal faces the ray's origin side.
  virtual SceneHit Intersect(const Eigen::Vector3d& o_world, const Eigen::Vector3d& d_unit,
                             double t_max_m) const = 0;

  /// World box enclosing the site's free space (the inside of its outer walls), metres.
  virtual Aabb Bounds() const = 0;

  /// Scanner (LiDAR) poses T_world_scanner, in scan order.
  virtual const std::vector<geometry::Pose>& Stations() const = 0;

  /// Viewpoints for render tests: in free space, at no station.
  virtual const std::vector<geometry::Pose>& NovelViews() const = 0;

  /// Linear RGB albedo of point x on face `face`, each channel in [0.05, 0.95].
  virtual Eigen::Vector3f Albedo(const Eigen::Vector3d& x_world, int face) const = 0;

  /// Analytic visibility, defined for every scene by its Intersect: true when the segment
  /// o → x meets no surface before x − eps_m (x itself may lie on a surface). False when x
  /// lies outside Bounds() grown by eps_m.
  bool Visible(const Eigen::Vector3d& o_world, const Eigen::Vector3d& x_world,
               double eps_m = 1e-6) const;

 protected:
  Scene() = default;
  Scene(const Scene&) = default;             // copy only as the derived type (no slicing)
  Scene& operator=(const Scene&) = default;
};

/// The canonical synthetic site: a 6 m × 5 m × 3 m room with one 0.8 m × 0.8 m × 1.8 m box,
/// optionally with extra solid boxes (WithExtraBox).
class SyntheticRoom final : public Scene {
 public:
  /// The canonical test scene (geometry, stations and novel views documented in the .cc).
  static SyntheticRoom Default();

  /// A copy of this room with one more solid box, seen by Intersect, Visible and FaceSamples
  /// like the occluder: the k-th extra box (k = 0, 1, … in the order added) has face ids
  /// ExtraBoxFace(k, side) = kFaceCount + 6·k + side and a smooth magenta texture (its own
  /// phase per box), albedo in [0.05, 0.95]. Stations and novel views stay the same; the
  /// caller keeps the box inside the room and away from them (an origin inside a box does
  /// not see it).
  SyntheticRoom WithExtraBox(const Aabb& box) const;

  /// A copy of this room whose every face is tiled: its albedo times a checker of `tile_m`
  /// squares on the face's own coordinates, 1 and 0.55 (a sharp texture, for the detectors
  /// that read a scene's darkest and brightest pixels, VASL-MODEL §9); `plain`: each face's
  /// base colour alone under the tiles (no sinusoid field or band). Not smooth: for tests
  /// that render it at a resolution that resolves the tiles.
  SyntheticRoom WithTiles(double tile_m, bool plain = false) const;

  /// Face id of side `side` (kBoxSide*) of extra box k.
  static int ExtraBoxFace(size_t k, int side) {
    return kFaceCount + kBoxSideCount * static_cast<int>(k) + side;
  }

  /// Interior of the room, world, metres.
  const Aabb& RoomBounds() const { return room_; }
  /// The solid occluding box standing on the floor, world, metres.
  const Aabb& OccluderBounds() const { return box_; }
  /// Extra solid boxes, in the order added (WithExtraBox), world, metres.
  const std::vector<Aabb>& ExtraBoxes() const { return extra_boxes_; }

  /// First hit of the ray o + t·d, 0 < t ≤ t_max_m. `d_unit` must be unit length. The origin
  /// is expected inside the room and outside the occluder and extra boxes (a box containing
  /// the origin is skipped).
  SceneHit Intersect(const Eigen::Vector3d& o_world, const Eigen::Vector3d& d_unit,
                     double t_max_m) const override;

  /// The room's interior (RoomBounds()).
  Aabb Bounds() const override { return room_; }

  /// Scanner (LiDAR) poses T_world_scanner: 4 stations 1.30–1.55 m above the floor, ≥ 1 m from
  /// the walls and the box, yawed. Station 0 sees the box in front of wall y = max (it casts a
  /// shadow there); station 1 sees that shadowed region lit.
  const std::vector<geometry::Pose>& Stations() const override { return stations_; }

  /// Viewpoints for render tests: inside the room, at no station, not inside the box.
  const std::vector<geometry::Pose>& NovelViews() const override { return novel_views_; }

  /// Linear RGB albedo of point x on face `face`, each channel in [0.05, 0.95]. Smooth: the
  /// finest feature (sinusoid wavelength, band edge width) is ≥ 0.3 m (unless WithTiles).
  /// Faces of extra boxes that do not exist, and other ids, give 0.05.
  Eigen::Vector3f Albedo(const Eigen::Vector3d& x_world, int face) const override;

  /// Unit normal of a face, pointing into the free space of the room (room faces inward, box
  /// faces, the extra boxes' included, outward). Zero for kFaceNone.
  static Eigen::Vector3d FaceNormal(int face);

  /// Points on `face` on a regular grid of pitch spacing_m, kept when they (and 8 neighbours
  /// at distance margin_m within the face plane) are visible from every origin in `lit_from`
  /// and hidden from every origin in `shadowed_from`. The face border (margin_m) is excluded.
  /// Faces of extra boxes are accepted too; other ids give no points.
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
  /// The box a face lies on: the room (room faces), the occluder or an extra box; nullptr for
  /// ids of no face.
  const Aabb* FaceBox(int face) const;

  Aabb room_;                               ///< interior of the room, world, metres
  Aabb box_;                                ///< the occluder, world, metres
  std::vector<Aabb> extra_boxes_;           ///< boxes added by WithExtraBox, world, metres
  double tile_m_ = 0.0;                     ///< WithTiles' square, metres; 0: no tiles
  bool plain_ = false;                      ///< WithTiles' plain faces
  std::vector<geometry::Pose> stations_;    ///< T_world_scanner per station
  std::vector<geometry::Pose> novel_views_; ///< render-test viewpoints
};

/// The pose of a rig's panoramic camera at a station: kCameraAboveLidarM above the LiDAR
/// (+z world), same orientation.
geometry::Pose CameraPoseForStation(const geometry::Pose& T_world_scanner);

/// Rec.709 luminance of a linear RGB triple (the synthetic LiDAR's reflectance).
float Luminance(const Eigen::Vector3f& rgb_linear);

/// PSNR (peak 1) of two linear RGB rasters (3 floats per pixel) over the pixels where `mask`
/// is set: how closely a render matches the truth or an input panorama.
double PsnrOver(const std::vector<float>& a, const std::vector<float>& b,
                const std::vector<bool>& mask);

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

  /// The 1080×540 grid the store and flow tests scan with (quick, and dense enough for
  /// h = 5 cm), with noise seed `seed`.
  static LidarSettings Small(uint64_t seed) {
    LidarSettings s;
    s.azimuth_steps = 1080;
    s.elevation_steps = 540;
    s.seed = seed;
    return s;
  }
};

/// True when row `j` of the ray grid lies outside the nadir blind cone (its centre's elevation
/// is at least −π/2 + nadir_blind_rad): GenerateLidar casts that row's rays.
bool LidarRowKept(const LidarSettings& settings, int j);

/// The range grid of a scan GenerateLidar casts with `settings`, as a scanner's row and column
/// indices (E57 rowIndex / columnIndex) give it: elevation_steps × azimuth_steps cells, and per
/// point its cell row·columns + column (the cell its direction falls in, so rays that returned
/// nothing leave their cells empty), into `lidar`.
void SetRangeGrid(const LidarSettings& settings, ingest::LidarData* lidar);

/// A LiDAR scan: points in the SENSOR frame, row-major over the ray grid (row 0 up).
struct LidarScan {
  std::vector<float> xyz_sensor_m;  ///< 3 floats per point, sensor frame, metres
  std::vector<float> intensity;     ///< 1 per point: reflectance in [0.05, 0.95]
  std::vector<float> rgb;           ///< 3 per point: linear albedo at the hit (a coloured scan)
};

/// Simulates a LiDAR at T_world_scanner: one return per ray, range = analytic range + noise.
LidarScan GenerateLidar(const Scene& scene, const geometry::Pose& T_world_scanner,
                        const LidarSettings& settings);

/// One LiDAR source per station of `scene` (ids 1, 2, … in station order, each scan seeded by
/// its id), points in the sensor frame with their intensities.
std::vector<ingest::LidarSource> StationLidars(const Scene& scene, LidarSettings settings);

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
Panorama RenderPanorama(const Scene& scene, const geometry::Pose& T_world_camera,
                        int width_px, int height_px, int supersample = 4);

/// T_world_camera of a pinhole camera (§2.2 frame: x right, y down, z forward) at `o` looking
/// at `target`, level (its x axis horizontal). `target` must not lie straight above or below.
geometry::Pose LookAt(const Eigen::Vector3d& o, const Eigen::Vector3d& target);

/// A survey photo's intrinsics: 640×480, about 65° across, with barrel distortion and a little
/// decentring, as a camera calibration gives them.
geometry::PinholeIntrinsics SurveyPhotoIntrinsics();

/// Renders the photo of a pinhole camera (§2.2: x right, y down, z forward; Brown–Conrady
/// distortion) at T_world_camera, k.width_px × k.height_px, pixel-integrated like
/// RenderPanorama; depth is the centre ray's range (not its z).
Panorama RenderPinhole(const Scene& scene, const geometry::Pose& T_world_camera,
                       const geometry::PinholeIntrinsics& k, int supersample = 4);

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

/// The scan of station `station` (an index into scene.Stations()) as a rig sends it, ready for
/// Engine::IngestScan: LiDAR points (seeded with lidar.seed) and the station camera's panorama
/// (pano_width_px × pano_width_px/2, pixel-integrated, encoded as PNG), named
/// "scan-<station+1>" with one panorama "cam0" (none when pano_width_px is 0). With
/// `point_colour` the points carry their albedo as colour (a coloured scan, as E57 files are).
absl::StatusOr<ingest::ScanInput> MakeScanInput(const Scene& scene, size_t station,
                                                const LidarSettings& lidar, int pano_width_px,
                                                int supersample = 4, bool point_colour = false);

/// A camera-only scan of one equirect panorama (rig "handheld"): `pano`, encoded as PNG, named
/// "pano", at `pose` (the scan's pose too), the scan named `name`.
absl::StatusOr<ingest::ScanInput> PanoramaScan(const std::string& name, const geometry::Pose& pose,
                                               const Panorama& pano);

/// A camera-only scan (no LiDAR points) named `name`, posed at `photo_pose`: a pinhole photo
/// "photo" (SurveyPhotoIntrinsics) at `photo_pose` and an equirect panorama "pano" of
/// pano_width_px × pano_width_px/2 at `pano_pose`, both pixel-integrated (supersample 2) and
/// encoded as PNG.
absl::StatusOr<ingest::ScanInput> MakeCameraOnlyScan(const Scene& scene, const std::string& name,
                                                     const geometry::Pose& photo_pose,
                                                     const geometry::Pose& pano_pose,
                                                     int pano_width_px);

}  // namespace vasl::scenes

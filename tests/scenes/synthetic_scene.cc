/// @file synthetic_scene.cc
/// @brief The canonical synthetic room, the ray-box helpers every Scene shares, the LiDAR and
///        panorama simulators, and the writers of the files a rig sends (PLY, PNG) and of the
///        ground truth (.npy).
#include "tests/scenes/synthetic_scene.h"

#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <fstream>
#include <limits>
#include <random>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "lattice/geometry/equirect.h"

namespace vasl::scenes {
namespace {

using Eigen::Vector3d;
using Eigen::Vector3f;

constexpr double kInf = std::numeric_limits<double>::infinity();

/// A pose from a position (metres) and a yaw about world +z (radians).
geometry::Pose YawPose(const Vector3d& position_m, double yaw_rad) {
  geometry::Pose pose;
  pose.q_world_sensor = Eigen::Quaterniond(Eigen::AngleAxisd(yaw_rad, Vector3d::UnitZ()));
  pose.o_world = position_m;
  return pose;
}

/// Parameters of one face's analytic albedo (see Albedo()).
struct FaceTexture {
  Vector3f base;          ///< colour multiplied by the sinusoid field, each channel in [0, 1]
  Vector3f band;          ///< colour of the soft broad band, each channel in [0, 1]
  double lambda_s_m;      ///< wavelength of the sinusoid along the face's first axis, metres
  double lambda_t_m;      ///< wavelength of the sinusoid along the face's second axis, metres
  double phase_s_rad;     ///< phase of the first sinusoid, radians
  double phase_t_rad;     ///< phase of the second sinusoid, radians
  int band_axis;          ///< 0: band varies along s, 1: along t
  double band_centre_m;   ///< band centre on its axis, metres
  double band_sigma_m;    ///< Gaussian half-width of the band, metres
};

/// Textures per face id. The finest scales are a 1.5 m wavelength (amplitude 0.3 of base) and a
/// band of σ = 0.4 m: smooth at the 0.3 m scale, so a 0.05 m-vossel render can reproduce them
/// (the albedo changes by < 0.08 over any 0.05 m step; RMS change ≈ 0.02).
/// The occluder is orange; the wall behind it (y = max) is blue-grey: a strong silhouette.
/// Extra boxes are magenta with a yellow band, at the occluder's scales (phase per box and side).
FaceTexture TextureOf(int face) {
  if (face >= kFaceCount) {
    const int k = (face - kFaceCount) / kBoxSideCount;
    const int side = (face - kFaceCount) % kBoxSideCount;
    return {{0.88f, 0.22f, 0.42f}, {0.95f, 0.78f, 0.30f}, 1.5, 1.6, side + 0.7 * k, 0.5, 1,
            1.2, 0.40};
  }
  static const FaceTexture kTextures[kFaceCount] = {
      // floor: warm grey-brown, cream band across x
      {{0.60f, 0.48f, 0.36f}, {0.92f, 0.86f, 0.70f}, 2.1, 1.7, 0.3, 1.1, 0, 1.6, 0.45},
      // ceiling: off-white, pale blue band across y
      {{0.88f, 0.88f, 0.82f}, {0.55f, 0.68f, 0.92f}, 2.5, 2.0, 1.7, 0.4, 1, 2.5, 0.50},
      // wall x = min: green, yellow band in height
      {{0.36f, 0.62f, 0.44f}, {0.95f, 0.90f, 0.45f}, 1.8, 1.6, 0.9, 2.2, 1, 2.2, 0.40},
      // wall x = max: mauve, sky band along y
      {{0.72f, 0.40f, 0.52f}, {0.40f, 0.72f, 0.92f}, 1.8, 1.6, 2.4, 0.2, 0, 3.5, 0.45},
      // wall y = min: lavender, orange band in height
      {{0.50f, 0.50f, 0.78f}, {0.92f, 0.60f, 0.30f}, 1.7, 1.5, 0.1, 1.3, 1, 0.9, 0.40},
      // wall y = max: blue-grey, pale band along x
      {{0.30f, 0.50f, 0.82f}, {0.85f, 0.90f, 0.95f}, 1.6, 1.5, 1.2, 2.9, 0, 4.6, 0.45},
      // occluder faces: orange, yellow band in height
      {{0.95f, 0.46f, 0.16f}, {0.95f, 0.82f, 0.20f}, 1.5, 1.6, 0.0, 0.5, 1, 1.2, 0.40},
      {{0.95f, 0.46f, 0.16f}, {0.95f, 0.82f, 0.20f}, 1.5, 1.6, 1.0, 0.5, 1, 1.2, 0.40},
      {{0.95f, 0.46f, 0.16f}, {0.95f, 0.82f, 0.20f}, 1.5, 1.6, 2.0, 0.5, 1, 1.2, 0.40},
      {{0.95f, 0.46f, 0.16f}, {0.95f, 0.82f, 0.20f}, 1.5, 1.6, 3.0, 0.5, 1, 1.2, 0.40},
      {{0.90f, 0.52f, 0.20f}, {0.95f, 0.82f, 0.20f}, 1.5, 1.5, 0.5, 1.5, 0, 3.0, 0.40},
      {{0.90f, 0.52f, 0.20f}, {0.95f, 0.82f, 0.20f}, 1.5, 1.5, 0.5, 1.5, 0, 3.0, 0.40},
  };
  return kTextures[face];
}

/// Axis (0, 1, 2) a face (≥ 0; extra boxes' faces included) is normal to.
int FaceAxis(int face) {
  static const int kAxis[kFaceCount] = {2, 2, 0, 0, 1, 1, 0, 0, 1, 1, 2, 2};
  if (face >= kFaceCount) return BoxSideAxis((face - kFaceCount) % kBoxSideCount);
  return kAxis[face];
}

/// The in-plane coordinates (s, t) of a face: the two world axes spanning it, in x, y, z order.
Eigen::Vector2d FaceCoords(const Vector3d& x, int face) {
  switch (FaceAxis(face)) {
    case 2:
      return {x.x(), x.y()};
    case 0:
      return {x.y(), x.z()};
    default:  // walls and box faces normal to y
      return {x.x(), x.z()};
  }
}

uint64_t SplitMix64(uint64_t x) {
  x += 0x9E3779B97F4A7C15ull;
  x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ull;
  x = (x ^ (x >> 27)) * 0x94D049BB133111EBull;
  return x ^ (x >> 31);
}

float LinearToSrgb(float c) {
  c = std::clamp(c, 0.0f, 1.0f);
  return c <= 0.0031308f ? 12.92f * c : 1.055f * std::pow(c, 1.0f / 2.4f) - 0.055f;
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// Boxes and visibility, shared by every Scene.
// ---------------------------------------------------------------------------------------------
Vector3d BoxSideNormal(int side) {
  Vector3d n = Vector3d::Zero();
  n[BoxSideAxis(side)] = BoxSideAtMax(side) ? 1.0 : -1.0;
  return n;
}

double DistanceToAabb(const Vector3d& x, const Aabb& box) {
  Vector3d d;
  for (int a = 0; a < 3; ++a) d[a] = std::max({box.min_m[a] - x[a], 0.0, x[a] - box.max_m[a]});
  return d.norm();
}

SlabInterval RaySlabInterval(const Aabb& box, const Vector3d& o, const Vector3d& d) {
  static const int kMinSide[3] = {kBoxSideXMin, kBoxSideYMin, kBoxSideBottom};
  static const int kMaxSide[3] = {kBoxSideXMax, kBoxSideYMax, kBoxSideTop};
  SlabInterval iv;
  double t_near = -kInf, t_far = kInf;
  int side_near = -1;
  for (int a = 0; a < 3; ++a) {
    if (d[a] == 0.0) {
      if (o[a] < box.min_m[a] || o[a] > box.max_m[a]) return iv;
      continue;
    }
    double t0 = (box.min_m[a] - o[a]) / d[a];
    double t1 = (box.max_m[a] - o[a]) / d[a];
    int s0 = kMinSide[a];
    if (t0 > t1) std::swap(t0, t1), s0 = kMaxSide[a];
    if (t0 > t_near) t_near = t0, side_near = s0;
    t_far = std::min(t_far, t1);
  }
  iv.hit = t_near <= t_far;
  iv.t_near_m = t_near;
  iv.t_far_m = t_far;
  iv.side_near = side_near;
  return iv;
}

BoxEntry RayEntersBox(const Aabb& box, const Vector3d& o, const Vector3d& d) {
  const SlabInterval iv = RaySlabInterval(box, o, d);
  BoxEntry entry;
  if (iv.hit && iv.t_near_m > 0.0) {
    entry.valid = true;
    entry.t_m = iv.t_near_m;
    entry.side = iv.side_near;
  }
  return entry;
}

bool Scene::Visible(const Vector3d& o, const Vector3d& x, double eps_m) const {
  const Aabb bounds = Bounds();
  for (int a = 0; a < 3; ++a) {
    if (x[a] < bounds.min_m[a] - eps_m || x[a] > bounds.max_m[a] + eps_m) return false;
  }
  const Vector3d delta = x - o;
  const double dist = delta.norm();
  if (dist <= eps_m) return true;
  const SceneHit hit = Intersect(o, delta / dist, dist);
  return !hit.valid || hit.t_m >= dist - eps_m;
}

// ---------------------------------------------------------------------------------------------
// The canonical scene.
//
// Room x ∈ [0, 6], y ∈ [0, 5], z ∈ [0, 3]. Occluder x ∈ [2.6, 3.4], y ∈ [2.3, 3.1],
// z ∈ [0, 1.8]. Station 0 at (3.0, 1.2, 1.40) looks at the box's y-min face from 1.1 m; the
// box's shadow from it on wall y = 5 spans roughly x ∈ [1.6, 4.4], z ∈ [0, 2.8] (LiDAR; the
// camera 0.1 m higher shifts the upper edge). Station 1 at (1.2, 3.9, 1.50) is beside the box
// and sees that region of the wall lit. Stations 2 and 3 complete the ring. Every station is
// yawed so that pose handling is exercised: a sensor-frame direction is not a world direction.
// ---------------------------------------------------------------------------------------------
SyntheticRoom SyntheticRoom::Default() {
  SyntheticRoom room;
  room.room_ = {Vector3d(0.0, 0.0, 0.0), Vector3d(6.0, 5.0, 3.0)};
  room.box_ = {Vector3d(2.6, 2.3, 0.0), Vector3d(3.4, 3.1, 1.8)};
  const double deg = M_PI / 180.0;
  room.stations_ = {
      YawPose({3.0, 1.2, 1.40}, 20.0 * deg),
      YawPose({1.2, 3.9, 1.50}, 135.0 * deg),
      YawPose({4.8, 1.2, 1.30}, -60.0 * deg),
      YawPose({4.6, 3.9, 1.55}, -150.0 * deg),
  };
  room.novel_views_ = {
      YawPose({2.0, 1.8, 1.45}, 30.0 * deg),
      YawPose({4.4, 2.2, 1.50}, -100.0 * deg),
  };
  return room;
}

SyntheticRoom SyntheticRoom::WithExtraBox(const Aabb& box) const {
  SyntheticRoom room = *this;
  room.extra_boxes_.push_back(box);
  return room;
}

const Aabb* SyntheticRoom::FaceBox(int face) const {
  if (face < 0) return nullptr;
  if (face < kFaceBoxXMin) return &room_;
  if (face < kFaceCount) return &box_;
  const size_t k = static_cast<size_t>(face - kFaceCount) / kBoxSideCount;
  return k < extra_boxes_.size() ? &extra_boxes_[k] : nullptr;
}

Vector3d SyntheticRoom::FaceNormal(int face) {
  // Room faces face inward (toward the room's free space), box faces face outward.
  static const double kSign[kFaceCount] = {+1, -1, +1, -1, +1, -1, -1, +1, -1, +1, +1, -1};
  if (face < 0) return Vector3d::Zero();
  if (face >= kFaceCount) return BoxSideNormal((face - kFaceCount) % kBoxSideCount);
  Vector3d n = Vector3d::Zero();
  n[FaceAxis(face)] = kSign[face];
  return n;
}

Vector3f SyntheticRoom::Albedo(const Vector3d& x_world, int face) const {
  if (FaceBox(face) == nullptr) return Vector3f::Constant(0.05f);
  const FaceTexture tex = TextureOf(face);
  const Eigen::Vector2d st = FaceCoords(x_world, face);
  // Sinusoid field in [0.1, 1.0]; soft band weight in [0, 0.8]; value in [0, 1] → [0.05, 0.95].
  const double field =
      plain_ ? 0.55
             : 0.55 + 0.30 * std::sin(2.0 * M_PI * st[0] / tex.lambda_s_m + tex.phase_s_rad) +
                   0.15 * std::cos(2.0 * M_PI * st[1] / tex.lambda_t_m + tex.phase_t_rad);
  const double z = (st[tex.band_axis] - tex.band_centre_m) / tex.band_sigma_m;
  const double b = plain_ ? 0.0 : 0.8 * std::exp(-z * z);
  const double tile =
      tile_m_ > 0.0 && (int(std::floor(st[0] / tile_m_)) + int(std::floor(st[1] / tile_m_))) % 2
          ? 0.55
          : 1.0;
  Vector3f rgb;
  for (int c = 0; c < 3; ++c) {
    const double v = (1.0 - b) * tex.base[c] * field + b * tex.band[c];
    rgb[c] = static_cast<float>(tile * (0.05 + 0.9 * std::clamp(v, 0.0, 1.0)));
  }
  return rgb;
}

SyntheticRoom SyntheticRoom::WithTiles(double tile_m, bool plain) const {
  SyntheticRoom room = *this;
  room.tile_m_ = tile_m;
  room.plain_ = plain;
  return room;
}

SceneHit SyntheticRoom::Intersect(const Vector3d& o, const Vector3d& d, double t_max_m) const {
  SceneHit hit;
  double t_best = kInf;
  int face_best = kFaceNone;
  // Room interior: the ray leaves through the nearest wall it heads to.
  static const int kRoomMinFace[3] = {kFaceWallXMin, kFaceWallYMin, kFaceFloor};
  static const int kRoomMaxFace[3] = {kFaceWallXMax, kFaceWallYMax, kFaceCeiling};
  for (int a = 0; a < 3; ++a) {
    if (d[a] > 0.0) {
      const double t = (room_.max_m[a] - o[a]) / d[a];
      if (t < t_best) t_best = t, face_best = kRoomMaxFace[a];
    } else if (d[a] < 0.0) {
      const double t = (room_.min_m[a] - o[a]) / d[a];
      if (t < t_best) t_best = t, face_best = kRoomMinFace[a];
    }
  }
  // Occluder, then extra boxes: slab entry (the origin is outside them). On an exact tie the
  // earlier surface keeps the hit.
  if (const BoxEntry e = RayEntersBox(box_, o, d); e.valid && e.t_m < t_best) {
    t_best = e.t_m;
    face_best = kFaceBoxXMin + e.side;
  }
  for (size_t k = 0; k < extra_boxes_.size(); ++k) {
    if (const BoxEntry e = RayEntersBox(extra_boxes_[k], o, d); e.valid && e.t_m < t_best) {
      t_best = e.t_m;
      face_best = ExtraBoxFace(k, e.side);
    }
  }
  if (face_best == kFaceNone || !(t_best > 0.0) || t_best > t_max_m) return hit;
  hit.valid = true;
  hit.t_m = t_best;
  hit.x_world = o + t_best * d;
  // Snap the coordinate normal to the face onto its plane exactly.
  const int axis = FaceAxis(face_best);
  const bool is_box = face_best >= kFaceBoxXMin;
  const bool is_max = is_box ? BoxSideAtMax((face_best - kFaceBoxXMin) % kBoxSideCount)
                             : face_best == kRoomMaxFace[axis];
  const Aabb& bounds = *FaceBox(face_best);
  hit.x_world[axis] = is_max ? bounds.max_m[axis] : bounds.min_m[axis];
  hit.face = face_best;
  hit.n_world = FaceNormal(face_best);
  hit.albedo_linear = Albedo(hit.x_world, face_best);
  hit.reflectance = Luminance(hit.albedo_linear);
  return hit;
}

std::vector<Vector3d> SyntheticRoom::FaceSamples(int face, double spacing_m, double margin_m,
                                                 const std::vector<Vector3d>& lit_from,
                                                 const std::vector<Vector3d>& shadowed_from) const {
  std::vector<Vector3d> out;
  if (FaceBox(face) == nullptr || !(spacing_m > 0.0)) return out;
  const int axis = FaceAxis(face);
  const bool is_box = face >= kFaceBoxXMin;
  const Aabb& bounds = *FaceBox(face);
  const Vector3d n = FaceNormal(face);
  // Room faces with inward normal +axis are at min; box faces with outward normal +axis at max.
  const bool at_max = is_box ? n[axis] > 0 : n[axis] < 0;
  const int a_s = axis == 0 ? 1 : 0;
  const int a_t = axis == 2 ? 1 : 2;
  const double plane = at_max ? bounds.max_m[axis] : bounds.min_m[axis];
  auto ok = [&](const Vector3d& p) {
    for (const Vector3d& o : lit_from) {
      if (!Visible(o, p, 1e-6)) return false;
    }
    for (const Vector3d& o : shadowed_from) {
      if (Visible(o, p, 1e-6)) return false;
    }
    return true;
  };
  for (double s = bounds.min_m[a_s] + margin_m; s <= bounds.max_m[a_s] - margin_m + 1e-9;
       s += spacing_m) {
    for (double t = bounds.min_m[a_t] + margin_m; t <= bounds.max_m[a_t] - margin_m + 1e-9;
         t += spacing_m) {
      Vector3d p;
      p[axis] = plane;
      p[a_s] = s;
      p[a_t] = t;
      bool all = ok(p);
      for (int k = 0; k < 8 && all && margin_m > 0.0; ++k) {
        const double ang = k * M_PI / 4.0;
        Vector3d q = p;
        q[a_s] += margin_m * std::cos(ang);
        q[a_t] += margin_m * std::sin(ang);
        all = ok(q);
      }
      if (all) out.push_back(p);
    }
  }
  return out;
}

std::vector<Vector3d> SyntheticRoom::ShadowSamples() const {
  const geometry::Pose& s0 = stations_[0];
  const geometry::Pose& s1 = stations_[1];
  return FaceSamples(kFaceWallYMax, 0.1, 0.15,
                     {s1.o_world, CameraPoseForStation(s1).o_world},
                     {s0.o_world, CameraPoseForStation(s0).o_world});
}

std::vector<Vector3d> SyntheticRoom::LitSamples() const {
  const geometry::Pose& s0 = stations_[0];
  const geometry::Pose& s1 = stations_[1];
  return FaceSamples(kFaceWallYMax, 0.1, 0.15,
                     {s0.o_world, CameraPoseForStation(s0).o_world, s1.o_world,
                      CameraPoseForStation(s1).o_world},
                     {});
}

geometry::Pose CameraPoseForStation(const geometry::Pose& T_world_scanner) {
  geometry::Pose camera = T_world_scanner;
  camera.o_world.z() += kCameraAboveLidarM;
  return camera;
}

float Luminance(const Vector3f& rgb) {
  return 0.2126f * rgb[0] + 0.7152f * rgb[1] + 0.0722f * rgb[2];
}

double PsnrOver(const std::vector<float>& a, const std::vector<float>& b,
                const std::vector<bool>& mask) {
  double se = 0.0;
  size_t n = 0;
  for (size_t p = 0; p < mask.size(); ++p) {
    if (!mask[p]) continue;
    for (int c = 0; c < 3; ++c) {
      const double d = double(a[3 * p + c]) - b[3 * p + c];
      se += d * d;
    }
    n += 3;
  }
  return 10.0 * std::log10(1.0 / (se / double(std::max<size_t>(n, 1))));
}

bool LidarRowKept(const LidarSettings& settings, int j) {
  const double psi = M_PI * (0.5 - (j + 0.5) / settings.elevation_steps);  // §2.1 row centre
  return psi >= -M_PI / 2.0 + settings.nadir_blind_rad;
}

void SetRangeGrid(const LidarSettings& settings, ingest::LidarData* lidar) {
  lidar->grid_rows = settings.elevation_steps;
  lidar->grid_columns = settings.azimuth_steps;
  lidar->grid_cell.clear();
  // Each point's cell is the one its direction falls in: rays cast from cell centres (§2.1), so
  // a scan with rays that returned nothing (the sky, beyond range) gets the cells of the rest.
  const geometry::EquirectSize grid{settings.azimuth_steps, settings.elevation_steps};
  const size_t n = lidar->xyz_sensor_m.size() / 3;
  lidar->grid_cell.reserve(n);
  for (size_t k = 0; k < n; ++k) {
    const Vector3d p(lidar->xyz_sensor_m[3 * k], lidar->xyz_sensor_m[3 * k + 1],
                     lidar->xyz_sensor_m[3 * k + 2]);
    const Eigen::Vector2d uv = geometry::EquirectProject(p.normalized(), grid);
    const int i = std::clamp(int(std::floor(uv.x())), 0, settings.azimuth_steps - 1);
    const int j = std::clamp(int(std::floor(uv.y())), 0, settings.elevation_steps - 1);
    lidar->grid_cell.push_back(uint32_t(j * settings.azimuth_steps + i));
  }
}

std::vector<ingest::LidarSource> StationLidars(const Scene& scene, LidarSettings settings) {
  std::vector<ingest::LidarSource> lidars;
  int id = 1;
  for (const geometry::Pose& pose : scene.Stations()) {
    settings.seed = uint64_t(id);
    LidarScan scan = GenerateLidar(scene, pose, settings);
    ingest::LidarSource src;
    src.id = id++;
    src.pose = pose;
    src.xyz_sensor_m = std::move(scan.xyz_sensor_m);
    src.intensity = std::move(scan.intensity);
    lidars.push_back(std::move(src));
  }
  return lidars;
}

LidarScan GenerateLidar(const Scene& scene, const geometry::Pose& T_world_scanner,
                        const LidarSettings& settings) {
  const geometry::EquirectSize grid{settings.azimuth_steps, settings.elevation_steps};
  const int rows = std::max(0, settings.elevation_steps);
  const int cols = std::max(0, settings.azimuth_steps);
  // Per-row outputs with a per-row RNG stream: the result does not depend on scheduling.
  std::vector<std::vector<float>> row_xyz(rows), row_int(rows), row_rgb(rows);
  tbb::parallel_for(tbb::blocked_range<int>(0, rows), [&](const tbb::blocked_range<int>& r) {
    for (int j = r.begin(); j < r.end(); ++j) {
      if (!LidarRowKept(settings, j)) continue;
      std::mt19937_64 rng(SplitMix64(settings.seed * 0x9E3779B97F4A7C15ull + j));
      std::normal_distribution<double> noise(0.0, settings.range_noise_m);
      std::vector<float>& xyz = row_xyz[j];
      std::vector<float>& inten = row_int[j];
      std::vector<float>& rgb = row_rgb[j];
      xyz.reserve(3 * cols);
      inten.reserve(cols);
      for (int i = 0; i < cols; ++i) {
        // §2.1 inverse at the ray-grid cell centre: the ray direction in the sensor frame.
        const Vector3d d_sensor = geometry::EquirectUnproject(i + 0.5, j + 0.5, grid);
        const Vector3d d_world = T_world_scanner.DirectionToWorld(d_sensor);
        const SceneHit hit =
            scene.Intersect(T_world_scanner.o_world, d_world, settings.max_range_m);
        const double n = noise(rng);  // drawn for every ray so streams stay aligned
        if (!hit.valid) continue;
        const double range = std::max(0.0, hit.t_m + n);
        const Vector3d p = range * d_sensor;
        xyz.push_back(static_cast<float>(p.x()));
        xyz.push_back(static_cast<float>(p.y()));
        xyz.push_back(static_cast<float>(p.z()));
        inten.push_back(hit.reflectance);
        rgb.insert(rgb.end(), hit.albedo_linear.data(), hit.albedo_linear.data() + 3);
      }
    }
  });
  LidarScan scan;
  size_t n = 0;
  for (const auto& v : row_int) n += v.size();
  scan.xyz_sensor_m.reserve(3 * n);
  scan.intensity.reserve(n);
  for (int j = 0; j < rows; ++j) {
    scan.xyz_sensor_m.insert(scan.xyz_sensor_m.end(), row_xyz[j].begin(), row_xyz[j].end());
    scan.intensity.insert(scan.intensity.end(), row_int[j].begin(), row_int[j].end());
    scan.rgb.insert(scan.rgb.end(), row_rgb[j].begin(), row_rgb[j].end());
  }
  return scan;
}

namespace {

// Renders an image of width × height pixels whose camera-frame ray at continuous pixel
// coordinates (u, v) is unproject(u, v): each pixel the mean albedo over supersample² strata
// of [i, i+1) × [j, j+1), depth the centre ray's range.
template <typename Unproject>
Panorama RenderImage(const Scene& scene, const geometry::Pose& T_world_camera, int width_px,
                     int height_px, int supersample, Unproject unproject) {
  Panorama pano;
  pano.width_px = std::max(0, width_px);
  pano.height_px = std::max(0, height_px);
  const int s = std::max(1, supersample);
  const size_t w = pano.width_px, h = pano.height_px;
  pano.rgb.assign(w * h * 3, 0.0f);
  pano.depth_m.assign(w * h, std::numeric_limits<float>::infinity());
  const Vector3d o = T_world_camera.o_world;
  const tbb::blocked_range<int> all_rows(0, pano.height_px);
  tbb::parallel_for(all_rows, [&](const tbb::blocked_range<int>& r) {
    for (int j = r.begin(); j < r.end(); ++j) {
      for (int i = 0; i < pano.width_px; ++i) {
        // Pixel integration: the mean over s × s strata of [i, i+1) × [j, j+1), each sampled
        // at its centre with the projection's inverse at continuous coordinates.
        Vector3d sum = Vector3d::Zero();
        int hits = 0;
        for (int b = 0; b < s; ++b) {
          for (int a = 0; a < s; ++a) {
            const Vector3d d = T_world_camera.DirectionToWorld(
                unproject(i + (a + 0.5) / s, j + (b + 0.5) / s).normalized());
            const SceneHit hit = scene.Intersect(o, d, kInf);
            if (!hit.valid) continue;
            sum += hit.albedo_linear.cast<double>();
            ++hits;
          }
        }
        const size_t p = static_cast<size_t>(j) * w + i;
        if (hits > 0) {
          for (int c = 0; c < 3; ++c) pano.rgb[3 * p + c] = static_cast<float>(sum[c] / hits);
        }
        const Vector3d d_centre =
            T_world_camera.DirectionToWorld(unproject(i + 0.5, j + 0.5).normalized());
        const SceneHit centre = scene.Intersect(o, d_centre, kInf);
        if (centre.valid) pano.depth_m[p] = static_cast<float>(centre.t_m);
      }
    }
  });
  return pano;
}

}  // namespace

Panorama RenderPanorama(const Scene& scene, const geometry::Pose& T_world_camera,
                        int width_px, int height_px, int supersample) {
  const geometry::EquirectSize size{std::max(0, width_px), std::max(0, height_px)};
  return RenderImage(scene, T_world_camera, width_px, height_px, supersample,
                     [&size](double u, double v) { return geometry::EquirectUnproject(u, v, size); });
}

geometry::Pose LookAt(const Eigen::Vector3d& o, const Eigen::Vector3d& target) {
  const Vector3d f = (target - o).normalized();
  const Vector3d r = f.cross(Vector3d::UnitZ()).normalized();
  Eigen::Matrix3d R;
  R.col(0) = r;
  R.col(1) = f.cross(r);  // down
  R.col(2) = f;
  geometry::Pose pose;
  pose.o_world = o;
  pose.q_world_sensor = Eigen::Quaterniond(R).normalized();
  return pose;
}

geometry::PinholeIntrinsics SurveyPhotoIntrinsics() {
  geometry::PinholeIntrinsics k;
  k.width_px = 640;
  k.height_px = 480;
  k.fx_px = k.fy_px = 500.0;
  k.cx_px = 322.0;
  k.cy_px = 238.0;
  k.k1 = -0.08;
  k.k2 = 0.01;
  k.p1 = 0.0005;
  k.p2 = -0.0003;
  return k;
}

Panorama RenderPinhole(const Scene& scene, const geometry::Pose& T_world_camera,
                       const geometry::PinholeIntrinsics& k, int supersample) {
  return RenderImage(scene, T_world_camera, k.width_px, k.height_px, supersample,
                     [&k](double u, double v) {
                       return geometry::PinholeUnproject(Eigen::Vector2d(u, v), k);
                     });
}

std::vector<uint8_t> ToSrgb8(const Panorama& pano) {
  std::vector<uint8_t> out(pano.rgb.size());
  for (size_t k = 0; k < pano.rgb.size(); ++k) {
    out[k] = static_cast<uint8_t>(std::lround(255.0f * LinearToSrgb(pano.rgb[k])));
  }
  return out;
}

absl::StatusOr<std::string> EncodePng(const Panorama& pano) {
  if (pano.width_px <= 0 || pano.height_px <= 0 ||
      pano.rgb.size() != static_cast<size_t>(pano.width_px) * pano.height_px * 3) {
    return absl::InvalidArgumentError(
        absl::StrCat("panorama must be W×H×3 with W, H > 0; got W=", pano.width_px,
                     " H=", pano.height_px, " and ", pano.rgb.size(), " rgb values"));
  }
  const std::vector<uint8_t> srgb = ToSrgb8(pano);
  std::vector<unsigned char> buffer;
  OIIO::Filesystem::IOVecOutput proxy(buffer);
  const std::string name = "panorama.png";  // selects the PNG writer; nothing touches disk
  auto out = OIIO::ImageOutput::create(name, &proxy);
  if (!out) {
    return absl::InternalError(absl::StrCat("OpenImageIO has no PNG writer: ", OIIO::geterror()));
  }
  OIIO::ImageSpec spec(pano.width_px, pano.height_px, 3, OIIO::TypeDesc::UINT8);
  spec.attribute("oiio:ColorSpace", "sRGB");
  if (!out->open(name, spec) || !out->write_image(OIIO::TypeDesc::UINT8, srgb.data()) ||
      !out->close()) {
    return absl::InternalError(absl::StrCat("PNG encoding failed: ", out->geterror()));
  }
  return std::string(buffer.begin(), buffer.end());
}

absl::Status WritePly(const LidarScan& scan, const std::filesystem::path& path) {
  const size_t n = scan.intensity.size();
  if (scan.xyz_sensor_m.size() != 3 * n) {
    return absl::InvalidArgumentError(absl::StrCat("LiDAR scan has ", scan.xyz_sensor_m.size(),
                                                   " coordinates for ", n,
                                                   " intensities; need 3 per point"));
  }
  std::ofstream f(path, std::ios::binary | std::ios::trunc);
  if (!f) return absl::UnavailableError(absl::StrCat("cannot write ", path.string()));
  f << "ply\nformat binary_little_endian 1.0\nelement vertex " << n
    << "\nproperty float x\nproperty float y\nproperty float z\nproperty float intensity\n"
       "end_header\n";
  static_assert(sizeof(float) == 4, "PLY float is 4 bytes");
  std::vector<float> rows(4 * n);
  for (size_t k = 0; k < n; ++k) {
    rows[4 * k + 0] = scan.xyz_sensor_m[3 * k + 0];
    rows[4 * k + 1] = scan.xyz_sensor_m[3 * k + 1];
    rows[4 * k + 2] = scan.xyz_sensor_m[3 * k + 2];
    rows[4 * k + 3] = scan.intensity[k];
  }
  // x86-64 and aarch64 hosts are little-endian, as the header declares.
  f.write(reinterpret_cast<const char*>(rows.data()),
          static_cast<std::streamsize>(rows.size() * sizeof(float)));
  f.close();
  if (!f) return absl::UnavailableError(absl::StrCat("write failed: ", path.string()));
  return absl::OkStatus();
}

absl::Status WriteNpy(const std::vector<float>& data, const std::vector<size_t>& shape,
                      const std::filesystem::path& path) {
  size_t count = 1;
  for (size_t d : shape) count *= d;
  if (count != data.size()) {
    return absl::InvalidArgumentError(absl::StrCat("npy shape (", absl::StrJoin(shape, ", "),
                                                   ") holds ", count, " values but data has ",
                                                   data.size()));
  }
  std::string shape_str = "(" + absl::StrJoin(shape, ", ") + (shape.size() == 1 ? ",)" : ")");
  std::string header =
      absl::StrCat("{'descr': '<f4', 'fortran_order': False, 'shape': ", shape_str, ", }");
  // Pad with spaces and a final newline so the data starts at a multiple of 64 bytes.
  const size_t preamble = 10;  // magic (6) + version (2) + header length (2)
  size_t total = preamble + header.size() + 1;
  header.append((64 - total % 64) % 64, ' ');
  header.push_back('\n');
  if (header.size() > 65535) return absl::InvalidArgumentError("npy header too long");
  std::ofstream f(path, std::ios::binary | std::ios::trunc);
  if (!f) return absl::UnavailableError(absl::StrCat("cannot write ", path.string()));
  const char magic[8] = {'\x93', 'N', 'U', 'M', 'P', 'Y', 1, 0};
  f.write(magic, 8);
  const uint16_t len = static_cast<uint16_t>(header.size());
  const char len_le[2] = {static_cast<char>(len & 0xff), static_cast<char>(len >> 8)};
  f.write(len_le, 2);
  f.write(header.data(), static_cast<std::streamsize>(header.size()));
  f.write(reinterpret_cast<const char*>(data.data()),
          static_cast<std::streamsize>(data.size() * sizeof(float)));
  f.close();
  if (!f) return absl::UnavailableError(absl::StrCat("write failed: ", path.string()));
  return absl::OkStatus();
}

absl::StatusOr<ingest::ScanInput> MakeScanInput(const Scene& scene, size_t station,
                                                const LidarSettings& lidar, int pano_width_px,
                                                int supersample, bool point_colour) {
  const geometry::Pose& pose = scene.Stations().at(station);
  LidarScan points = GenerateLidar(scene, pose, lidar);
  ingest::ScanInput scan;
  scan.scan_name = "scan-" + std::to_string(station + 1);
  scan.rig = "synthetic-rig";
  scan.pose = pose;
  scan.lidar.xyz_sensor_m = std::move(points.xyz_sensor_m);
  scan.lidar.intensity = std::move(points.intensity);
  if (point_colour) scan.lidar.rgb = std::move(points.rgb);
  if (pano_width_px <= 0) return scan;
  ingest::PanoramaData pano;
  pano.name = "cam0";
  pano.pose = CameraPoseForStation(pose);
  absl::StatusOr<std::string> png =
      EncodePng(RenderPanorama(scene, pano.pose, pano_width_px, pano_width_px / 2, supersample));
  if (!png.ok()) return png.status();
  pano.encoded_image = std::move(*png);
  scan.panoramas.push_back(std::move(pano));
  return scan;
}

absl::StatusOr<ingest::ScanInput> MakeCameraOnlyScan(const Scene& scene, const std::string& name,
                                                     const geometry::Pose& photo_pose,
                                                     const geometry::Pose& pano_pose,
                                                     int pano_width_px) {
  ingest::ScanInput scan;
  scan.scan_name = name;
  scan.rig = "handheld";
  scan.pose = photo_pose;
  ingest::PanoramaData photo;
  photo.name = "photo";
  photo.pose = photo_pose;
  photo.pinhole = SurveyPhotoIntrinsics();
  absl::StatusOr<std::string> photo_png = EncodePng(RenderPinhole(scene, photo_pose, *photo.pinhole, 2));
  if (!photo_png.ok()) return photo_png.status();
  photo.encoded_image = std::move(*photo_png);
  ingest::PanoramaData pano;
  pano.name = "pano";
  pano.pose = pano_pose;
  absl::StatusOr<std::string> pano_png =
      EncodePng(RenderPanorama(scene, pano_pose, pano_width_px, pano_width_px / 2, 2));
  if (!pano_png.ok()) return pano_png.status();
  pano.encoded_image = std::move(*pano_png);
  scan.panoramas = {std::move(photo), std::move(pano)};
  return scan;
}

absl::StatusOr<ingest::ScanInput> PanoramaScan(const std::string& name, const geometry::Pose& pose,
                                               const Panorama& pano) {
  ingest::ScanInput scan;
  scan.scan_name = name;
  scan.rig = "handheld";
  scan.pose = pose;
  ingest::PanoramaData data;
  data.name = "pano";
  data.pose = pose;
  absl::StatusOr<std::string> png = EncodePng(pano);
  if (!png.ok()) return png.status();
  data.encoded_image = std::move(*png);
  scan.panoramas = {std::move(data)};
  return scan;
}

}  // namespace vasl::scenes

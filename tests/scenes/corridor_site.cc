/// @file corridor_site.cc
/// @brief The canonical corridor site: layout, exact ray caster and analytic albedos.
#include "tests/scenes/corridor_site.h"

#include <algorithm>
#include <cassert>
#include <cmath>
#include <limits>

#include <Eigen/Geometry>

namespace vasl::scenes {
namespace {

using Eigen::Vector3d;
using Eigen::Vector3f;

constexpr double kInf = std::numeric_limits<double>::infinity();

// Dimensions of CorridorSite::Default(), metres.
constexpr int kRooms = 4;
constexpr double kRoomLengthM = 5.0;  // along x
constexpr double kRoomWidthM = 4.0;   // along y
constexpr double kRoomHeightM = 3.0;
constexpr double kWallM = 0.12;       // partition wall thickness
constexpr double kDoorWidthM = 1.0;
constexpr double kDoorHeightM = 2.1;

/// A pose from a position (metres) and a yaw about world +z (radians).
geometry::Pose YawPose(const Vector3d& position_m, double yaw_rad) {
  geometry::Pose pose;
  pose.q_world_sensor = Eigen::Quaterniond(Eigen::AngleAxisd(yaw_rad, Vector3d::UnitZ()));
  pose.o_world = position_m;
  return pose;
}

/// How a face's albedo varies over its plane (see Shade()).
enum class Pattern { kSmooth, kStripes, kChecker };

/// One face's analytic albedo: colours a and b (each channel in [0, 1]) mixed by a pattern.
struct Material {
  Pattern pattern = Pattern::kSmooth;  ///< how a and b are mixed
  Vector3f a = Vector3f::Constant(0.5f);  ///< first colour, each channel in [0, 1]
  Vector3f b = Vector3f::Constant(0.5f);  ///< second colour, each channel in [0, 1]
  /// Smooth: wavelength along s (1.3× along t), metres. Stripes and checker: the period (two
  /// stripes / two squares), metres.
  double period_m = 1.5;
  int axis = 0;          ///< stripes: 0 vary along s, 1 along t
  double phase_m = 0.0;  ///< offset of the pattern along s, metres
};

Material Smooth(const Vector3f& a, const Vector3f& b, double wavelength_m, double phase_m) {
  return {Pattern::kSmooth, a, b, wavelength_m, 0, phase_m};
}
Material Stripes(const Vector3f& a, const Vector3f& b, double period_m, int axis) {
  return {Pattern::kStripes, a, b, period_m, axis, 0.0};
}
Material Checker(const Vector3f& a, const Vector3f& b, double period_m) {
  return {Pattern::kChecker, a, b, period_m, 0, 0.0};
}

/// Parity (0 or 1) of floor(u / half_period_m), for any sign of u.
int HalfPeriodParity(double u, double period_m) {
  const long long k = static_cast<long long>(std::floor(u / (0.5 * period_m)));
  return static_cast<int>(((k % 2) + 2) % 2);
}

/// Evaluates a material at in-plane coordinates (s, t) and maps [0, 1] to [0.05, 0.95].
Vector3f Shade(const Material& m, double s, double t) {
  double w = 0.0;
  switch (m.pattern) {
    case Pattern::kSmooth:
      w = 0.5 + 0.5 * std::sin(2.0 * M_PI * (s + m.phase_m) / m.period_m) *
                    std::cos(2.0 * M_PI * t / (1.3 * m.period_m));
      break;
    case Pattern::kStripes:
      w = HalfPeriodParity((m.axis == 0 ? s : t) + m.phase_m, m.period_m);
      break;
    case Pattern::kChecker:
      w = (HalfPeriodParity(s + m.phase_m, m.period_m) + HalfPeriodParity(t, m.period_m)) % 2;
      break;
  }
  Vector3f rgb;
  for (int c = 0; c < 3; ++c) {
    const double v = (1.0 - w) * m.a[c] + w * m.b[c];
    rgb[c] = static_cast<float>(0.05 + 0.9 * std::clamp(v, 0.0, 1.0));
  }
  return rgb;
}

/// Per-room palette: wall colours (a, b) and the floor's dark tile colour.
struct RoomPalette {
  Vector3f wall_a;      ///< main wall colour
  Vector3f wall_b;      ///< lighter wall colour
  Vector3f floor_dark;  ///< dark floor tiles
};

const RoomPalette& PaletteOf(int room) {
  static const RoomPalette kPalettes[4] = {
      {{0.85f, 0.72f, 0.52f}, {0.95f, 0.88f, 0.70f}, {0.30f, 0.22f, 0.18f}},  // beige
      {{0.50f, 0.75f, 0.55f}, {0.80f, 0.92f, 0.70f}, {0.18f, 0.30f, 0.22f}},  // green
      {{0.50f, 0.65f, 0.90f}, {0.80f, 0.85f, 0.95f}, {0.20f, 0.22f, 0.34f}},  // blue
      {{0.90f, 0.55f, 0.65f}, {0.95f, 0.82f, 0.75f}, {0.34f, 0.18f, 0.24f}},  // pink
  };
  return kPalettes[((room % 4) + 4) % 4];
}

/// In-plane coordinates (s, t) of a face normal to `axis`: the two other world axes, in order.
Eigen::Vector2d PlaneCoords(const Vector3d& x, int axis) {
  if (axis == 2) return {x.x(), x.y()};
  if (axis == 0) return {x.y(), x.z()};
  return {x.x(), x.z()};
}

/// Axis and max-side flag of an envelope face (0–5).
int EnvelopeAxis(int face) {
  static const int kAxis[6] = {2, 2, 0, 0, 1, 1};
  return kAxis[face];
}
bool EnvelopeAtMax(int face) {
  return face == kCorridorFaceCeiling || face == kCorridorFaceEndXMax ||
         face == kCorridorFaceLongYMax;
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// The canonical corridor site.
//
// Room i (i = 0..3) is x ∈ [5.12·i, 5.12·i + 5], y ∈ [0, 4], z ∈ [0, 3]; partition wall i
// (between rooms i and i+1) fills x ∈ [5.12·i + 5, 5.12·(i+1)] with a door y ∈ [1, 2]
// (i even) or [2, 3] (i odd), z ∈ [0, 2.1]. The site spans x ∈ [0, 20.36].
//
// Furniture, in room-local coordinates (lx = x − 5.12·i; ly = y in even rooms, 4 − y in odd
// rooms, i.e. odd rooms are mirrored):
//   table: top lx ∈ [0.4, 1.6], ly ∈ [3.0, 3.7], z ∈ [0.73, 0.75] (2 cm); legs 5 cm square,
//          inset 5 cm, z ∈ [0, 0.73];
//   pillar: lx ∈ [2.6, 2.85], ly ∈ [2.3, 2.55], z ∈ [0, 2.5];
//   large box: lx ∈ [3.7, 4.7], ly ∈ [0.2, 1.0], z ∈ [0, 1.0 + 0.2·i].
// Stations, local: A (1.0, 1.6), B (3.8, 3.0), C (2.8, 1.2); heights 1.20–1.70 m and yaws all
// different (lists below). Each is ≥ 1.0 m from the walls and ≥ 0.8 m from every solid; each
// sees the door(s) of its room. Novel views, local: (1.9, 2.6) in even rooms, (4.2, 1.9) in odd.
// ---------------------------------------------------------------------------------------------
CorridorSite CorridorSite::Default() {
  CorridorSite site;
  const double pitch = kRoomLengthM + kWallM;
  auto room_x0 = [&](int i) { return pitch * i; };
  site.envelope_ = {Vector3d(0.0, 0.0, 0.0),
                    Vector3d(room_x0(kRooms - 1) + kRoomLengthM, kRoomWidthM, kRoomHeightM)};
  for (int i = 0; i < kRooms; ++i) {
    site.rooms_.push_back({Vector3d(room_x0(i), 0.0, 0.0),
                           Vector3d(room_x0(i) + kRoomLengthM, kRoomWidthM, kRoomHeightM)});
  }
  // Partition walls: the pieces around each door.
  for (int p = 0; p + 1 < kRooms; ++p) {
    const double x0 = site.rooms_[p].max_m.x(), x1 = site.rooms_[p + 1].min_m.x();
    const double y0 = p % 2 == 0 ? 1.0 : 2.0, y1 = y0 + kDoorWidthM;
    site.solids_.push_back({{Vector3d(x0, 0.0, 0.0), Vector3d(x1, y0, kRoomHeightM)},
                            SolidKind::kWall, p});
    site.solids_.push_back({{Vector3d(x0, y1, 0.0), Vector3d(x1, kRoomWidthM, kRoomHeightM)},
                            SolidKind::kWall, p});
    site.solids_.push_back({{Vector3d(x0, y0, kDoorHeightM), Vector3d(x1, y1, kRoomHeightM)},
                            SolidKind::kLintel, p});
    site.doors_.push_back({{Vector3d(x0, y0, 0.0), Vector3d(x1, y1, kDoorHeightM)}, p, p + 1});
    site.groups_.push_back({{}, static_cast<int>(site.solids_.size()) - 3, 3});
  }
  // Furniture, from room-local boxes (odd rooms mirrored in y).
  for (int i = 0; i < kRooms; ++i) {
    const bool mirror = i % 2 == 1;
    auto local = [&](double lx0, double lx1, double ly0, double ly1, double z0, double z1) {
      const double y0 = mirror ? kRoomWidthM - ly1 : ly0;
      const double y1 = mirror ? kRoomWidthM - ly0 : ly1;
      return Aabb{Vector3d(room_x0(i) + lx0, y0, z0), Vector3d(room_x0(i) + lx1, y1, z1)};
    };
    const int first = static_cast<int>(site.solids_.size());
    site.solids_.push_back({local(0.4, 1.6, 3.0, 3.7, 0.73, 0.75), SolidKind::kTableTop, i});
    for (const double lx : {0.45, 1.50}) {
      for (const double ly : {3.05, 3.60}) {
        site.solids_.push_back(
            {local(lx, lx + 0.05, ly, ly + 0.05, 0.0, 0.73), SolidKind::kTableLeg, i});
      }
    }
    site.solids_.push_back({local(2.6, 2.85, 2.3, 2.55, 0.0, 2.5), SolidKind::kPillar, i});
    site.solids_.push_back({local(3.7, 4.7, 0.2, 1.0, 0.0, 1.0 + 0.2 * i), SolidKind::kBox, i});
    site.groups_.push_back({{}, first, static_cast<int>(site.solids_.size()) - first});
  }
  // Culling groups' bounds: the union of their members.
  for (SolidGroup& g : site.groups_) {
    g.bounds = site.solids_[g.first].box;
    for (int b = g.first + 1; b < g.first + g.count; ++b) {
      g.bounds.min_m = g.bounds.min_m.cwiseMin(site.solids_[b].box.min_m);
      g.bounds.max_m = g.bounds.max_m.cwiseMax(site.solids_[b].box.max_m);
    }
  }
  assert(static_cast<int>(site.groups_.size()) <= kMaxGroups);
  // Stations: A, B, C per room (local), heights and yaws all different.
  const double deg = M_PI / 180.0;
  static const double kLocalXy[3][2] = {{1.0, 1.6}, {3.8, 3.0}, {2.8, 1.2}};
  static const double kHeightM[12] = {1.20, 1.55, 1.35, 1.70, 1.25, 1.45,
                                      1.60, 1.30, 1.50, 1.40, 1.65, 1.22};
  static const double kYawDeg[12] = {15, 140, -70, -160, 60, 100, -25, 170, -115, 35, -50, 125};
  for (int i = 0; i < kRooms; ++i) {
    for (int k = 0; k < 3; ++k) {
      const int s = 3 * i + k;
      const double y = i % 2 == 1 ? kRoomWidthM - kLocalXy[k][1] : kLocalXy[k][1];
      site.stations_.push_back(
          YawPose({room_x0(i) + kLocalXy[k][0], y, kHeightM[s]}, kYawDeg[s] * deg));
    }
  }
  static const double kNovelHeightM[4] = {1.45, 1.50, 1.40, 1.55};
  static const double kNovelYawDeg[4] = {30, -100, 160, -45};
  for (int i = 0; i < kRooms; ++i) {
    const bool odd = i % 2 == 1;
    const double lx = odd ? 4.2 : 1.9, ly = odd ? 1.9 : 2.6;
    site.novel_views_.push_back(YawPose(
        {room_x0(i) + lx, odd ? kRoomWidthM - ly : ly, kNovelHeightM[i]}, kNovelYawDeg[i] * deg));
  }
  return site;
}

int CorridorSite::RoomAt(const Vector3d& x) const {
  for (int i = 0; i < RoomCount(); ++i) {
    bool inside = true;
    for (int a = 0; a < 3; ++a) {
      inside = inside && x[a] >= rooms_[i].min_m[a] && x[a] <= rooms_[i].max_m[a];
    }
    if (inside) return i;
  }
  return -1;
}

Vector3d CorridorSite::FaceNormal(int face) {
  if (face < 0) return Vector3d::Zero();
  if (face >= kCorridorFirstSolidFace) {
    return BoxSideNormal((face - kCorridorFirstSolidFace) % kBoxSideCount);
  }
  Vector3d n = Vector3d::Zero();
  n[EnvelopeAxis(face)] = EnvelopeAtMax(face) ? -1.0 : 1.0;  // inward
  return n;
}

std::string CorridorSite::KindName(SolidKind kind) {
  switch (kind) {
    case SolidKind::kWall:
      return "wall";
    case SolidKind::kLintel:
      return "lintel";
    case SolidKind::kTableTop:
      return "table_top";
    case SolidKind::kTableLeg:
      return "table_leg";
    case SolidKind::kPillar:
      return "pillar";
    case SolidKind::kBox:
      return "box";
  }
  return "unknown";
}

Vector3f CorridorSite::Albedo(const Vector3d& x, int face) const {
  if (face < 0) return Vector3f::Constant(0.05f);
  Material m;
  int axis = 0;
  if (face < kCorridorFirstSolidFace) {
    // Envelope: the colours of the room x lies in (a partition's thickness, where the room
    // changes, is hidden inside the wall).
    int room = RoomCount() - 1;
    for (int i = 0; i + 1 < RoomCount(); ++i) {
      if (x.x() < 0.5 * (rooms_[i].max_m.x() + rooms_[i + 1].min_m.x())) {
        room = i;
        break;
      }
    }
    const RoomPalette& pal = PaletteOf(room);
    axis = EnvelopeAxis(face);
    switch (face) {
      case kCorridorFaceFloor:
        m = Checker({0.78f, 0.74f, 0.66f}, pal.floor_dark, 0.4);
        break;
      case kCorridorFaceCeiling:
        m = Smooth({0.92f, 0.92f, 0.88f}, {0.82f, 0.86f, 0.92f}, 2.5, 0.3);
        break;
      case kCorridorFaceEndXMin:
      case kCorridorFaceEndXMax:
        m = Smooth(pal.wall_a, pal.wall_b, 1.7, 0.2 + 0.5 * face);
        break;
      case kCorridorFaceLongYMin:
        m = Smooth(pal.wall_a, pal.wall_b, 2.0, 0.7 * room);
        break;
      default:  // kCorridorFaceLongYMax
        m = room % 2 == 0 ? Stripes(pal.wall_a, {0.95f, 0.95f, 0.92f}, 0.30, 0)
                          : Stripes(pal.wall_a, {0.95f, 0.95f, 0.92f}, 0.25, 1);
        break;
    }
  } else {
    const size_t b = static_cast<size_t>(SolidOfFace(face));
    if (b >= solids_.size()) return Vector3f::Constant(0.05f);
    const int side = (face - kCorridorFirstSolidFace) % kBoxSideCount;
    axis = BoxSideAxis(side);
    const CorridorSolid& solid = solids_[b];
    switch (solid.kind) {
      case SolidKind::kWall:
      case SolidKind::kLintel:
        if (axis == 0) {  // faces into a room: that room's colours
          const RoomPalette& pal = PaletteOf(solid.room + (side == kBoxSideXMax ? 1 : 0));
          m = Smooth(pal.wall_b, pal.wall_a, 1.5, 0.4 * solid.room);
        } else {  // door jambs and the lintel's soffit
          m = Smooth({0.70f, 0.70f, 0.68f}, {0.82f, 0.82f, 0.80f}, 1.4, 0.0);
        }
        break;
      case SolidKind::kTableTop:
        m = axis == 2 ? Stripes({0.72f, 0.48f, 0.26f}, {0.52f, 0.32f, 0.16f}, 0.20, 0)
                      : Smooth({0.45f, 0.28f, 0.14f}, {0.55f, 0.35f, 0.18f}, 1.5, 0.0);
        break;
      case SolidKind::kTableLeg:
        m = Smooth({0.15f, 0.15f, 0.17f}, {0.25f, 0.25f, 0.28f}, 1.5, 0.0);
        break;
      case SolidKind::kPillar:
        m = axis == 2 ? Smooth({0.85f, 0.85f, 0.85f}, {0.70f, 0.70f, 0.75f}, 1.5, 0.0)
                      : Stripes({0.92f, 0.92f, 0.90f}, {0.18f, 0.22f, 0.45f}, 0.35, 1);
        break;
      case SolidKind::kBox:
        m = Checker({0.90f, 0.55f, 0.20f}, {0.25f, 0.50f, 0.35f}, 0.30);
        break;
    }
  }
  const Eigen::Vector2d st = PlaneCoords(x, axis);
  return Shade(m, st[0], st[1]);
}

SceneHit CorridorSite::Intersect(const Vector3d& o, const Vector3d& d, double t_max_m) const {
  SceneHit hit;
  double t_best = kInf;
  int face_best = kFaceNone;
  // Envelope: the ray leaves through the nearest envelope face it heads to.
  static const int kMinFace[3] = {kCorridorFaceEndXMin, kCorridorFaceLongYMin,
                                  kCorridorFaceFloor};
  static const int kMaxFace[3] = {kCorridorFaceEndXMax, kCorridorFaceLongYMax,
                                  kCorridorFaceCeiling};
  for (int a = 0; a < 3; ++a) {
    if (d[a] > 0.0) {
      const double t = (envelope_.max_m[a] - o[a]) / d[a];
      if (t < t_best) t_best = t, face_best = kMaxFace[a];
    } else if (d[a] < 0.0) {
      const double t = (envelope_.min_m[a] - o[a]) / d[a];
      if (t < t_best) t_best = t, face_best = kMinFace[a];
    }
  }
  // Solids: the nearest entry. Groups are visited nearest first and skipped once they start
  // beyond the best hit; a member's entry is never before its group's (RaySlabInterval is
  // monotone), so this is exactly the minimum over all solids. An exact tie keeps the solid
  // visited first.
  struct Candidate {
    double t_m;  ///< where the ray enters the group's bounds (0 if it starts inside)
    int group;   ///< index into groups_
  };
  Candidate candidates[kMaxGroups];
  int n = 0;
  for (int g = 0; g < static_cast<int>(groups_.size()); ++g) {
    const SlabInterval iv = RaySlabInterval(groups_[g].bounds, o, d);
    if (!iv.hit || !(iv.t_far_m > 0.0)) continue;
    const double t_enter = std::max(iv.t_near_m, 0.0);
    if (!(t_enter < t_best)) continue;
    int k = n++;  // insertion sort by entry (stable)
    for (; k > 0 && candidates[k - 1].t_m > t_enter; --k) candidates[k] = candidates[k - 1];
    candidates[k] = {t_enter, g};
  }
  for (int c = 0; c < n && candidates[c].t_m < t_best; ++c) {
    const SolidGroup& g = groups_[candidates[c].group];
    for (int b = g.first; b < g.first + g.count; ++b) {
      if (const BoxEntry e = RayEntersBox(solids_[b].box, o, d); e.valid && e.t_m < t_best) {
        t_best = e.t_m;
        face_best = SolidFace(b, e.side);
      }
    }
  }
  if (face_best == kFaceNone || !(t_best > 0.0) || t_best > t_max_m) return hit;
  hit.valid = true;
  hit.t_m = t_best;
  hit.x_world = o + t_best * d;
  // Snap the coordinate normal to the face onto its plane exactly.
  const int solid = SolidOfFace(face_best);
  if (solid < 0) {
    const int axis = EnvelopeAxis(face_best);
    hit.x_world[axis] =
        EnvelopeAtMax(face_best) ? envelope_.max_m[axis] : envelope_.min_m[axis];
  } else {
    const int side = (face_best - kCorridorFirstSolidFace) % kBoxSideCount;
    const int axis = BoxSideAxis(side);
    const Aabb& box = solids_[solid].box;
    hit.x_world[axis] = BoxSideAtMax(side) ? box.max_m[axis] : box.min_m[axis];
  }
  hit.face = face_best;
  hit.n_world = FaceNormal(face_best);
  hit.albedo_linear = Albedo(hit.x_world, face_best);
  hit.reflectance = Luminance(hit.albedo_linear);
  return hit;
}

}  // namespace vasl::scenes

// Claims of the corridor site (tests/scenes/corridor_site.h) and of SyntheticRoom::WithExtraBox:
// the layout meets its specification; Intersect is exact (it equals a slow per-face reference)
// and agrees with Visible; a station sees its own room and, through the doors only, part of its
// neighbours; LiDAR points lie on the analytic surfaces within the noise; scans span several
// 64-vossel tiles; panoramas hold albedo in range; an extra box hides the wall behind it.
#include "tests/scenes/corridor_site.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <random>
#include <set>
#include <tuple>
#include <vector>

#include <gtest/gtest.h>

#include "tests/scenes/synthetic_scene.h"

namespace vasl::scenes {
namespace {

using Eigen::Vector3d;
using Eigen::Vector3f;

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kVosselM = 0.05;  // h
constexpr int kTileVossels = 64;   // a tile is 64 vossels = 3.2 m at h = 0.05 m

/// A slow, obviously correct reference hit: every face rectangle of the site (envelope faces
/// facing inward, solid faces outward) met by the ray from its front side, nearest first.
struct RefHit {
  double t_m = kInf;    ///< distance along the ray, metres (+inf: none)
  int face = kFaceNone; ///< face id
};

RefHit SlowReferenceHit(const CorridorSite& site, const Vector3d& o, const Vector3d& d) {
  RefHit best;
  auto try_face = [&](int face, const Aabb& box, int axis, double plane) {
    const Vector3d n = CorridorSite::FaceNormal(face);
    if (!(n.dot(d) < 0.0)) return;  // seen from behind or edge-on
    const double t = (plane - o[axis]) / d[axis];
    if (!(t > 0.0) || !(t < best.t_m)) return;
    const Vector3d x = o + t * d;
    for (int a = 0; a < 3; ++a) {
      if (a == axis) continue;
      if (x[a] < box.min_m[a] || x[a] > box.max_m[a]) return;
    }
    best = {t, face};
  };
  const Aabb env = site.Bounds();
  static const int kEnvelopeFaces[6][2] = {{kCorridorFaceFloor, 2},    {kCorridorFaceCeiling, 2},
                                           {kCorridorFaceEndXMin, 0},  {kCorridorFaceEndXMax, 0},
                                           {kCorridorFaceLongYMin, 1}, {kCorridorFaceLongYMax, 1}};
  for (const auto& [face, axis] : kEnvelopeFaces) {
    const bool at_max = CorridorSite::FaceNormal(face)[axis] < 0.0;
    try_face(face, env, axis, at_max ? env.max_m[axis] : env.min_m[axis]);
  }
  for (size_t b = 0; b < site.Solids().size(); ++b) {
    const Aabb& box = site.Solids()[b].box;
    for (int side = 0; side < kBoxSideCount; ++side) {
      const int axis = BoxSideAxis(side);
      try_face(CorridorSite::SolidFace(b, side), box, axis,
               BoxSideAtMax(side) ? box.max_m[axis] : box.min_m[axis]);
    }
  }
  return best;
}

/// Shortest distance from x to the walls of room `room` (its interior's x and y faces).
double DistanceToRoomWalls(const CorridorSite& site, int room, const Vector3d& x) {
  const Aabb& r = site.RoomInterior(room);
  return std::min({x.x() - r.min_m.x(), r.max_m.x() - x.x(), x.y() - r.min_m.y(),
                   r.max_m.y() - x.y()});
}

/// Room whose x-range, grown by margin_m at both ends, holds x (a LiDAR point on a floor or a
/// partition face, with range noise), −1 if none (inside a partition wall).
int RoomOfX(const CorridorSite& site, const Vector3d& x, double margin_m) {
  for (int i = 0; i < site.RoomCount(); ++i) {
    const Aabb& r = site.RoomInterior(i);
    if (x.x() >= r.min_m.x() - margin_m && x.x() <= r.max_m.x() + margin_m) return i;
  }
  return -1;
}

double Yaw(const geometry::Pose& pose) {
  const Vector3d fwd = pose.DirectionToWorld(Vector3d::UnitX());
  return std::atan2(fwd.y(), fwd.x());
}

/// LiDAR settings of the scan-based tests: 0.5° pitch, seeded per station.
LidarSettings TestLidar(size_t station) {
  LidarSettings s;
  s.azimuth_steps = 720;
  s.elevation_steps = 360;
  s.seed = 100 + station;
  return s;
}

/// One scan per station of CorridorSite::Default() (TestLidar), generated once.
const std::vector<LidarScan>& Scans() {
  static const std::vector<LidarScan>* scans = [] {
    const CorridorSite site = CorridorSite::Default();
    auto* out = new std::vector<LidarScan>;
    for (size_t s = 0; s < site.Stations().size(); ++s) {
      out->push_back(GenerateLidar(site, site.Stations()[s], TestLidar(s)));
    }
    return out;
  }();
  return *scans;
}

/// World point k of a scan taken at `pose`.
Vector3d WorldPoint(const LidarScan& scan, const geometry::Pose& pose, size_t k) {
  return pose.SensorToWorld(Vector3d(scan.xyz_sensor_m[3 * k], scan.xyz_sensor_m[3 * k + 1],
                                     scan.xyz_sensor_m[3 * k + 2]));
}

// Claim: the site is the specified one: ≥ 4 rooms of about 5 × 4 × 3 m in a row along +x
// spanning ≥ 20 m, joined by 1 m × 2.1 m doors; 12 stations, 3 per room, 1.2–1.7 m high, all
// yawed differently, ≥ 0.8 m from walls and solids; the furniture includes a 2 cm table top
// at 0.75 m, a tall narrow pillar and a large box; novel views lie in rooms, clear of solids
// and stations; albedo stays in [0.05, 0.95], sharp-edged on the patterned faces (a jump
// ≥ 0.1 across 1 mm) and smooth on the others (< 0.05 per 0.05 m step within one room: the
// envelope's colours change from room to room inside the partition walls, where no one sees).
TEST(CorridorSiteTest, LayoutMeetsSpecification) {
  const CorridorSite site = CorridorSite::Default();
  const Aabb bounds = site.Bounds();
  ASSERT_GE(site.RoomCount(), 4);
  EXPECT_GE(bounds.max_m.x() - bounds.min_m.x(), 20.0);
  for (int i = 0; i < site.RoomCount(); ++i) {
    const Vector3d size = site.RoomInterior(i).max_m - site.RoomInterior(i).min_m;
    EXPECT_NEAR(size.x(), 5.0, 0.5);
    EXPECT_NEAR(size.y(), 4.0, 0.5);
    EXPECT_NEAR(size.z(), 3.0, 0.3);
    if (i > 0) EXPECT_GT(site.RoomInterior(i).min_m.x(), site.RoomInterior(i - 1).max_m.x());
  }
  ASSERT_EQ(site.Doors().size(), static_cast<size_t>(site.RoomCount() - 1));
  for (size_t p = 0; p < site.Doors().size(); ++p) {
    const CorridorDoor& door = site.Doors()[p];
    EXPECT_EQ(door.room_xmin, static_cast<int>(p));
    EXPECT_EQ(door.room_xmax, static_cast<int>(p) + 1);
    EXPECT_NEAR(door.opening.max_m.y() - door.opening.min_m.y(), 1.0, 0.1);
    EXPECT_NEAR(door.opening.max_m.z() - door.opening.min_m.z(), 2.1, 1e-12);
    EXPECT_EQ(door.opening.min_m.z(), 0.0);
    EXPECT_EQ(door.opening.min_m.x(), site.RoomInterior(p).max_m.x());
    EXPECT_EQ(door.opening.max_m.x(), site.RoomInterior(p + 1).min_m.x());
  }

  const auto& stations = site.Stations();
  ASSERT_GE(stations.size(), 12u);
  std::vector<int> per_room(site.RoomCount(), 0);
  for (size_t s = 0; s < stations.size(); ++s) {
    const Vector3d o = stations[s].o_world;
    const int room = site.RoomAt(o);
    ASSERT_EQ(room, site.StationRoom(s)) << "station " << s;
    ++per_room[room];
    EXPECT_GE(o.z(), 1.2 - 1e-12);
    EXPECT_LE(o.z(), 1.7 + 1e-12);
    double nearest_solid = kInf;
    for (const CorridorSolid& solid : site.Solids()) {
      nearest_solid = std::min(nearest_solid, DistanceToAabb(o, solid.box));
    }
    const double walls = DistanceToRoomWalls(site, room, o);
    EXPECT_GE(walls, 0.8) << "station " << s;
    EXPECT_GE(nearest_solid, 0.8) << "station " << s;
    for (size_t r = 0; r < s; ++r) {
      double dyaw = std::abs(Yaw(stations[s]) - Yaw(stations[r]));
      dyaw = std::min(dyaw, 2 * M_PI - dyaw);
      EXPECT_GT(dyaw, 5.0 * M_PI / 180.0) << "stations " << r << " and " << s;
    }
    std::printf("station %2zu: room %d, (%.2f, %.2f, %.2f), yaw %6.1f°, %.2f m from walls, "
                "%.2f m from solids\n",
                s, room, o.x(), o.y(), o.z(), Yaw(stations[s]) * 180 / M_PI, walls,
                nearest_solid);
  }
  for (int count : per_room) EXPECT_EQ(count, 3);

  bool thin_top = false, pillar = false, big_box = false;
  for (const CorridorSolid& solid : site.Solids()) {
    const Vector3d size = solid.box.max_m - solid.box.min_m;
    if (solid.kind == SolidKind::kTableTop && std::abs(size.z() - 0.02) < 1e-9 &&
        std::abs(solid.box.max_m.z() - 0.75) < 1e-9) {
      thin_top = true;
    }
    if (solid.kind == SolidKind::kPillar && size.z() >= 2.0 && size.x() <= 0.3 &&
        size.y() <= 0.3) {
      pillar = true;
    }
    if (solid.kind == SolidKind::kBox && size.prod() >= 0.8) big_box = true;
  }
  EXPECT_TRUE(thin_top);
  EXPECT_TRUE(pillar);
  EXPECT_TRUE(big_box);

  ASSERT_GE(site.NovelViews().size(), 1u);
  for (const geometry::Pose& v : site.NovelViews()) {
    const int room = site.RoomAt(v.o_world);
    ASSERT_GE(room, 0);
    EXPECT_GE(DistanceToRoomWalls(site, room, v.o_world), 0.3);
    for (const CorridorSolid& solid : site.Solids()) {
      EXPECT_GT(DistanceToAabb(v.o_world, solid.box), 0.3);
    }
    for (const geometry::Pose& s : stations) {
      EXPECT_GT((v.o_world - s.o_world).norm(), 0.5);
      EXPECT_GT((v.o_world - CameraPoseForStation(s).o_world).norm(), 0.5);
    }
  }

  // Albedo: range on every face, sharp and smooth faces as documented.
  std::mt19937_64 rng(7);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  auto random_point = [&] {
    return Vector3d(bounds.min_m.x() + u(rng) * (bounds.max_m.x() - bounds.min_m.x()),
                    bounds.min_m.y() + u(rng) * (bounds.max_m.y() - bounds.min_m.y()),
                    bounds.min_m.z() + u(rng) * (bounds.max_m.z() - bounds.min_m.z()));
  };
  const int face_count = CorridorSite::SolidFace(site.Solids().size(), 0);
  float lo = 1.0f, hi = 0.0f;
  for (int face = 0; face < face_count; ++face) {
    for (int k = 0; k < 2000; ++k) {
      const Vector3f a = site.Albedo(random_point(), face);
      lo = std::min(lo, a.minCoeff());
      hi = std::max(hi, a.maxCoeff());
    }
  }
  // Worst change over a step of `step_m` in the face plane, over random points.
  auto worst_change = [&](int face, double step_m) {
    const int axis = face < kCorridorFirstSolidFace
                         ? (face < 2 ? 2 : (face < 4 ? 0 : 1))
                         : BoxSideAxis((face - kCorridorFirstSolidFace) % kBoxSideCount);
    double worst = 0.0;
    for (int k = 0; k < 20000; ++k) {
      const Vector3d x = random_point();
      Vector3d step(u(rng) - 0.5, u(rng) - 0.5, u(rng) - 0.5);
      step[axis] = 0.0;
      step = step_m * step.normalized();
      const int room = RoomOfX(site, x, 0.0);
      if (room < 0 || RoomOfX(site, x + step, 0.0) != room) continue;
      worst = std::max(
          worst, static_cast<double>((site.Albedo(x + step, face) - site.Albedo(x, face))
                                         .cwiseAbs()
                                         .maxCoeff()));
    }
    return worst;
  };
  auto face_of_kind = [&](SolidKind kind, int side) {
    for (size_t b = 0; b < site.Solids().size(); ++b) {
      if (site.Solids()[b].kind == kind) return CorridorSite::SolidFace(b, side);
    }
    return kFaceNone;
  };
  const int sharp[] = {kCorridorFaceFloor, kCorridorFaceLongYMax,
                       face_of_kind(SolidKind::kTableTop, kBoxSideTop),
                       face_of_kind(SolidKind::kPillar, kBoxSideXMin),
                       face_of_kind(SolidKind::kBox, kBoxSideYMax)};
  const int smooth[] = {kCorridorFaceCeiling, kCorridorFaceLongYMin, kCorridorFaceEndXMin,
                        face_of_kind(SolidKind::kWall, kBoxSideXMin),
                        face_of_kind(SolidKind::kTableLeg, kBoxSideXMin)};
  for (int face : sharp) {
    const double jump = worst_change(face, 0.001);
    std::printf("sharp face %d: worst change over 1 mm %.3f\n", face, jump);
    EXPECT_GE(jump, 0.1) << "face " << face;
  }
  for (int face : smooth) {
    const double step = worst_change(face, 0.05);
    std::printf("smooth face %d: worst change over 0.05 m %.4f\n", face, step);
    EXPECT_LT(step, 0.05) << "face " << face;
  }
  std::printf("albedo range over %d faces: [%.3f, %.3f]\n", face_count, lo, hi);
  EXPECT_GE(lo, 0.05f);
  EXPECT_LE(hi, 0.95f);
}

// Claim: Intersect is exact: over random rays from every station and novel view, it returns
// the same distance (1e-9 m) and face as a slow per-face reference (faces may differ only on
// an exact tie at an edge: ≤ 0.01% of rays), the hit lies on its face plane with the normal
// facing the ray; and Visible agrees with it: the hit is visible, a point 1 cm before it is
// visible, a point 1 cm behind it is not; for random targets Visible equals "the reference
// finds no face before the target".
TEST(CorridorSiteTest, IntersectIsExactAndAgreesWithVisible) {
  const CorridorSite site = CorridorSite::Default();
  std::vector<Vector3d> origins;
  for (const auto& s : site.Stations()) {
    origins.push_back(s.o_world);
    origins.push_back(CameraPoseForStation(s).o_world);
  }
  for (const auto& v : site.NovelViews()) origins.push_back(v.o_world);
  std::mt19937_64 rng(21);
  std::normal_distribution<double> g(0.0, 1.0);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  const Aabb bounds = site.Bounds();
  size_t rays = 0, t_mismatch = 0, face_mismatch = 0, off_plane = 0, wrong_normal = 0;
  size_t hit_not_visible = 0, before_not_visible = 0, behind_visible = 0;
  size_t targets = 0, visible_mismatch = 0, visible_count = 0;
  for (const Vector3d& o : origins) {
    for (int k = 0; k < 8000; ++k) {
      const Vector3d d = Vector3d(g(rng), g(rng), g(rng)).normalized();
      const SceneHit hit = site.Intersect(o, d, kInf);
      ++rays;
      ASSERT_TRUE(hit.valid);  // a closed site
      const RefHit ref = SlowReferenceHit(site, o, d);
      if (std::abs(ref.t_m - hit.t_m) > 1e-9) ++t_mismatch;
      if (ref.face != hit.face) ++face_mismatch;
      if ((o + hit.t_m * d - hit.x_world).norm() > 1e-9) ++off_plane;
      if (!(hit.n_world.dot(d) < 0.0)) ++wrong_normal;
      if (!site.Visible(o, hit.x_world)) ++hit_not_visible;
      if (hit.t_m > 0.02 && !site.Visible(o, o + (hit.t_m - 0.01) * d)) ++before_not_visible;
      if (site.Visible(o, o + (hit.t_m + 0.01) * d)) ++behind_visible;
      // A random target inside the bounds (possibly inside a solid).
      const Vector3d x(bounds.min_m.x() + u(rng) * (bounds.max_m.x() - bounds.min_m.x()),
                       bounds.min_m.y() + u(rng) * (bounds.max_m.y() - bounds.min_m.y()),
                       bounds.min_m.z() + u(rng) * (bounds.max_m.z() - bounds.min_m.z()));
      const double dist = (x - o).norm();
      const RefHit to_x = SlowReferenceHit(site, o, (x - o) / dist);
      const bool ref_visible = to_x.t_m >= dist - 1e-6;
      const bool visible = site.Visible(o, x);
      ++targets;
      visible_count += visible;
      visible_mismatch += visible != ref_visible;
    }
  }
  std::printf("%zu rays from %zu origins: t mismatches %zu, face mismatches %zu, off plane %zu, "
              "normal not facing the ray %zu; hit not visible %zu, 1 cm before not visible %zu, "
              "1 cm behind visible %zu; %zu random targets (%zu visible): Visible vs reference "
              "mismatches %zu\n",
              rays, origins.size(), t_mismatch, face_mismatch, off_plane, wrong_normal,
              hit_not_visible, before_not_visible, behind_visible, targets, visible_count,
              visible_mismatch);
  EXPECT_EQ(t_mismatch, 0u);
  EXPECT_LE(face_mismatch, rays / 10000);
  EXPECT_EQ(off_plane, 0u);
  EXPECT_EQ(wrong_normal, 0u);
  EXPECT_EQ(hit_not_visible, 0u);
  EXPECT_EQ(before_not_visible, 0u);
  EXPECT_EQ(behind_visible, 0u);
  EXPECT_EQ(visible_mismatch, 0u);
  EXPECT_GT(visible_count, targets / 10);  // the comparison is not vacuous
}

// Claim: every station sees its own room's far long wall: on a 0.1 m grid over that wall
// (within the room, 0.1 m border excluded) ≥ 70% of the points are visible, and the ray to each
// visible point hits that wall at exactly that point (1e-9 m). Of the station's LiDAR points
// ≥ 90% land in its own room (its x-range, grown by 1 cm for the range noise).
TEST(CorridorSiteTest, StationSeesItsOwnRoomsFarWall) {
  const CorridorSite site = CorridorSite::Default();
  for (size_t s = 0; s < site.Stations().size(); ++s) {
    const geometry::Pose& pose = site.Stations()[s];
    const Vector3d o = pose.o_world;
    const Aabb& room = site.RoomInterior(site.StationRoom(s));
    const bool far_is_ymax = room.max_m.y() - o.y() > o.y() - room.min_m.y();
    const double y_wall = far_is_ymax ? room.max_m.y() : room.min_m.y();
    const int face = far_is_ymax ? kCorridorFaceLongYMax : kCorridorFaceLongYMin;
    size_t total = 0, visible = 0, wrong_hit = 0;
    for (double x = room.min_m.x() + 0.1; x <= room.max_m.x() - 0.1 + 1e-9; x += 0.1) {
      for (double z = 0.1; z <= room.max_m.z() - 0.1 + 1e-9; z += 0.1) {
        const Vector3d p(x, y_wall, z);
        ++total;
        if (!site.Visible(o, p)) continue;
        ++visible;
        const SceneHit hit = site.Intersect(o, (p - o).normalized(), kInf);
        if (hit.face != face || (hit.x_world - p).norm() > 1e-9) ++wrong_hit;
      }
    }
    const LidarScan& scan = Scans()[s];
    size_t own = 0;
    for (size_t k = 0; k < scan.intensity.size(); ++k) {
      own += RoomOfX(site, WorldPoint(scan, pose, k), 0.01) == site.StationRoom(s);
    }
    const double frac_wall = static_cast<double>(visible) / total;
    const double frac_own = static_cast<double>(own) / scan.intensity.size();
    std::printf("station %2zu: far wall y = %.0f: %zu of %zu grid points visible (%.1f%%); "
                "%.1f%% of LiDAR points in its own room\n",
                s, y_wall, visible, total, 100 * frac_wall, 100 * frac_own);
    EXPECT_GE(frac_wall, 0.7) << "station " << s;
    EXPECT_EQ(wrong_hit, 0u) << "station " << s;
    EXPECT_GE(frac_own, 0.9) << "station " << s;
  }
}

// Claim: through a door a station sees part of the next room and the partition wall hides the
// rest. For every station and every neighbouring room: the ray through the centre of the
// door's lower half (z = 0.5 m) passes and lands in the neighbour room; a target in the
// neighbour room whose segment crosses the partition ≥ 0.2 m outside the opening is hidden,
// and the ray towards it stops on the partition's face (at the wall plane, 1e-9 m). Of each
// station's LiDAR points, some (≥ 0.2%) land in a neighbouring room, but few (≤ 10%).
TEST(CorridorSiteTest, DoorsRevealPartOfTheNextRoomAndWallsHideTheRest) {
  const CorridorSite site = CorridorSite::Default();
  for (size_t s = 0; s < site.Stations().size(); ++s) {
    const geometry::Pose& pose = site.Stations()[s];
    const Vector3d o = pose.o_world;
    const int room = site.StationRoom(s);
    for (const CorridorDoor& door : site.Doors()) {
      if (door.room_xmin != room && door.room_xmax != room) continue;
      const int next = door.room_xmin == room ? door.room_xmax : door.room_xmin;
      const Aabb& gap = door.opening;
      // The face of the partition towards the station.
      const double wall_x = next > room ? gap.min_m.x() : gap.max_m.x();
      const Vector3d centre(0.5 * (gap.min_m.x() + gap.max_m.x()),
                            0.5 * (gap.min_m.y() + gap.max_m.y()), 0.5);
      EXPECT_TRUE(site.Visible(o, centre)) << "station " << s << " → door to room " << next;
      const SceneHit through = site.Intersect(o, (centre - o).normalized(), kInf);
      ASSERT_TRUE(through.valid);
      EXPECT_EQ(RoomOfX(site, through.x_world, 0.0), next)
          << "station " << s << " through the door hits (" << through.x_world.transpose()
          << ")";
      // A hidden target: the segment crosses the partition plane outside the opening.
      const Aabb& far_room = site.RoomInterior(next);
      bool found = false;
      for (double y : {0.5, 3.5}) {
        for (double z : {1.0, 1.5}) {
          const Vector3d q(0.5 * (far_room.min_m.x() + far_room.max_m.x()), y, z);
          const double f = (wall_x - o.x()) / (q.x() - o.x());
          const Vector3d cross = o + f * (q - o);
          const double outside = std::max({gap.min_m.y() - cross.y(), cross.y() - gap.max_m.y(),
                                           cross.z() - gap.max_m.z()});
          if (outside < 0.2 || !site.Visible(o, cross)) continue;  // in the door, or blocked
          found = true;
          EXPECT_FALSE(site.Visible(o, q)) << "station " << s << " target " << q.transpose();
          const SceneHit hit = site.Intersect(o, (q - o).normalized(), kInf);
          const int b = CorridorSite::SolidOfFace(hit.face);
          ASSERT_GE(b, 0);
          const CorridorSolid& solid = site.Solids()[b];
          EXPECT_TRUE(solid.kind == SolidKind::kWall || solid.kind == SolidKind::kLintel);
          EXPECT_EQ(solid.room, std::min(room, next));
          EXPECT_NEAR(hit.x_world.x(), wall_x, 1e-9);
          EXPECT_NEAR((hit.x_world - cross).norm(), 0.0, 1e-9);
        }
      }
      EXPECT_TRUE(found) << "station " << s << ": no hidden target behind the wall to room "
                         << next;
    }
    const LidarScan& scan = Scans()[s];
    size_t neighbour = 0;
    for (size_t k = 0; k < scan.intensity.size(); ++k) {
      const int r = RoomOfX(site, WorldPoint(scan, pose, k), 0.01);
      neighbour += r >= 0 && std::abs(r - room) == 1;
    }
    const double frac = static_cast<double>(neighbour) / scan.intensity.size();
    std::printf("station %2zu (room %d): %.2f%% of LiDAR points in a neighbouring room\n", s,
                room, 100 * frac);
    EXPECT_GE(frac, 0.002) << "station " << s;
    EXPECT_LE(frac, 0.10) << "station " << s;
  }
}

// Claim: every LiDAR point of every station lies on the analytic surface along its own ray,
// within the range noise: ≥ 99.9% within 4σ, residual mean within 0.1σ, its σ within 5% of the
// setting; intensity is the luminance of the albedo at the hit; every ray outside the nadir
// cone returns (a closed site). A full 1440 × 720 scan takes < 1 s and is deterministic.
TEST(CorridorSiteTest, LidarPointsLieOnAnalyticSurfaces) {
  const CorridorSite site = CorridorSite::Default();
  for (size_t s = 0; s < site.Stations().size(); ++s) {
    const geometry::Pose& pose = site.Stations()[s];
    const LidarSettings settings = TestLidar(s);
    const double sigma = settings.range_noise_m;
    const LidarScan& scan = Scans()[s];
    const size_t n = scan.intensity.size();
    ASSERT_EQ(scan.xyz_sensor_m.size(), 3 * n);
    int kept_rows = 0;
    for (int j = 0; j < settings.elevation_steps; ++j) kept_rows += LidarRowKept(settings, j);
    EXPECT_EQ(n, static_cast<size_t>(kept_rows) * settings.azimuth_steps);
    size_t within = 0, wrong_intensity = 0;
    double sum = 0.0, sum2 = 0.0;
    for (size_t k = 0; k < n; ++k) {
      const Vector3d p(scan.xyz_sensor_m[3 * k], scan.xyz_sensor_m[3 * k + 1],
                       scan.xyz_sensor_m[3 * k + 2]);
      const double range = p.norm();
      const SceneHit hit = site.Intersect(pose.o_world, pose.DirectionToWorld(p / range), kInf);
      ASSERT_TRUE(hit.valid);
      const double res = range - hit.t_m;
      sum += res;
      sum2 += res * res;
      within += std::abs(res) <= 4.0 * sigma;
      wrong_intensity += std::abs(scan.intensity[k] -
                                  Luminance(site.Albedo(hit.x_world, hit.face))) > 1e-6;
    }
    const double mean = sum / n, sd = std::sqrt(sum2 / n - mean * mean);
    const double frac = static_cast<double>(within) / n;
    std::printf("station %2zu: %zu points, %.4f%% within 4σ, residual mean %.2e m, σ %.3e m\n",
                s, n, 100 * frac, mean, sd);
    EXPECT_GE(frac, 0.999);
    EXPECT_LT(std::abs(mean), 0.1 * sigma);
    EXPECT_NEAR(sd, sigma, 0.05 * sigma);
    EXPECT_EQ(wrong_intensity, 0u);
  }
  LidarSettings full;
  full.azimuth_steps = 1440;
  full.elevation_steps = 720;
  full.seed = 5;
  // Deterministic: the same seed gives the same scan (speed is measured in deploy/bench.sh).
  const LidarScan a = GenerateLidar(site, site.Stations()[0], full);
  const LidarScan b = GenerateLidar(site, site.Stations()[0], full);
  std::printf("1440x720 scan of station 0: %zu points\n", a.intensity.size());
  EXPECT_EQ(a.xyz_sensor_m, b.xyz_sensor_m);
  EXPECT_EQ(a.intensity, b.intensity);
}

// Claim: at h = 0.05 m (vossel centres at h·k, §1; tiles of 64 vossels = 3.2 m), every station's
// scan spans more than one tile, and the 12 stations together cover ≥ 6 tiles along x.
TEST(CorridorSiteTest, ScansSpanSeveralTiles) {
  const CorridorSite site = CorridorSite::Default();
  auto tile = [](double x_m) {
    const long long k = static_cast<long long>(std::floor(x_m / kVosselM + 0.5));
    return static_cast<int>(k >= 0 ? k / kTileVossels : -((-k + kTileVossels - 1) / kTileVossels));
  };
  std::set<int> all_x;
  for (size_t s = 0; s < site.Stations().size(); ++s) {
    const geometry::Pose& pose = site.Stations()[s];
    const LidarScan& scan = Scans()[s];
    std::set<std::tuple<int, int, int>> tiles;
    std::set<int> xs;
    for (size_t k = 0; k < scan.intensity.size(); ++k) {
      const Vector3d x = WorldPoint(scan, pose, k);
      tiles.insert({tile(x.x()), tile(x.y()), tile(x.z())});
      xs.insert(tile(x.x()));
    }
    all_x.insert(xs.begin(), xs.end());
    std::printf("station %2zu: %zu tiles, x tiles %d..%d\n", s, tiles.size(), *xs.begin(),
                *xs.rbegin());
    EXPECT_GT(tiles.size(), 1u) << "station " << s;
  }
  std::printf("all stations: %zu tiles along x\n", all_x.size());
  EXPECT_GE(all_x.size(), 6u);
}

// Claim: panoramas of the corridor site hold the albedo: every pixel of every station camera
// and novel view (256 × 128, 2 × 2 sub-pixel rays) is in [0.05, 0.95] (no pixel misses the
// site), with a finite positive depth; the renders differ between rooms.
TEST(CorridorSiteTest, PanoramasHoldAlbedoInRange) {
  const CorridorSite site = CorridorSite::Default();
  std::vector<geometry::Pose> cams;
  for (const auto& s : site.Stations()) cams.push_back(CameraPoseForStation(s));
  for (const auto& v : site.NovelViews()) cams.push_back(v);
  std::vector<Eigen::Vector3d> means;
  for (const geometry::Pose& cam : cams) {
    const Panorama pano = RenderPanorama(site, cam, 256, 128, 2);
    float lo = 1.0f, hi = 0.0f;
    Eigen::Vector3d mean = Eigen::Vector3d::Zero();
    size_t bad_depth = 0;
    for (size_t p = 0; p < pano.depth_m.size(); ++p) {
      for (int c = 0; c < 3; ++c) {
        lo = std::min(lo, pano.rgb[3 * p + c]);
        hi = std::max(hi, pano.rgb[3 * p + c]);
        mean[c] += pano.rgb[3 * p + c];
      }
      bad_depth += !(std::isfinite(pano.depth_m[p]) && pano.depth_m[p] > 0.0f);
    }
    means.push_back(mean / pano.depth_m.size());
    EXPECT_GE(lo, 0.05f);
    EXPECT_LE(hi, 0.95f);
    EXPECT_EQ(bad_depth, 0u);
  }
  // Rooms are coloured differently: first stations of rooms 0 and 2 (beige vs blue).
  const double diff = (means[0] - means[6]).norm();
  std::printf("%zu panoramas in range; mean colour distance room 0 vs room 2: %.3f\n",
              cams.size(), diff);
  EXPECT_GT(diff, 0.03);
}

// Claim (SyntheticRoom::WithExtraBox): a box added in front of wall y = max hides it: rays that
// hit the wall now hit the box (a face id ExtraBoxFace(0, side) ≥ kFaceCount, the point on that
// side's plane), nearer; the wall point turns invisible; the box's albedo is in range; rays
// that miss the box are unchanged (bit for bit); stations, novel views and the default room
// are unchanged; a later LiDAR scan sees the box.
TEST(SyntheticRoomTest, WithExtraBoxHidesTheWallBehindIt) {
  const SyntheticRoom room = SyntheticRoom::Default();
  const Aabb extra{Vector3d(1.8, 4.5, 0.0), Vector3d(2.4, 4.8, 1.2)};
  const SyntheticRoom later = room.WithExtraBox(extra);
  EXPECT_TRUE(room.ExtraBoxes().empty());
  ASSERT_EQ(later.ExtraBoxes().size(), 1u);
  ASSERT_EQ(later.Stations().size(), room.Stations().size());
  for (size_t s = 0; s < room.Stations().size(); ++s) {
    EXPECT_EQ(later.Stations()[s].o_world, room.Stations()[s].o_world);
    EXPECT_TRUE(later.Stations()[s].q_world_sensor.isApprox(room.Stations()[s].q_world_sensor,
                                                            0.0));
    EXPECT_GE(DistanceToAabb(room.Stations()[s].o_world, extra), 0.8);
  }
  EXPECT_EQ(later.NovelViews().size(), room.NovelViews().size());
  const int box_face = SyntheticRoom::ExtraBoxFace(0, kBoxSideYMin);
  EXPECT_GE(box_face, kFaceCount);
  EXPECT_EQ(SyntheticRoom::FaceNormal(box_face), Vector3d(0, -1, 0));

  const double y_wall = room.RoomBounds().max_m.y();
  const Vector3d c = 0.5 * (extra.min_m + extra.max_m);
  int checked = 0;
  for (const geometry::Pose& station : room.Stations()) {
    const Vector3d o = station.o_world;
    // The wall point behind the box's centre, as seen from this station.
    const Vector3d p = o + (c - o) * ((y_wall - o.y()) / (c.y() - o.y()));
    const Vector3d d = (p - o).normalized();
    const SceneHit before = room.Intersect(o, d, kInf);
    if (before.face != kFaceWallYMax) continue;  // the old occluder is in the way
    ++checked;
    EXPECT_NEAR((before.x_world - p).norm(), 0.0, 1e-9);
    EXPECT_TRUE(room.Visible(o, p));
    const SceneHit after = later.Intersect(o, d, kInf);
    const int side = after.face - SyntheticRoom::ExtraBoxFace(0, 0);
    ASSERT_GE(side, 0);
    ASSERT_LT(side, kBoxSideCount);
    const int axis = BoxSideAxis(side);
    EXPECT_EQ(after.x_world[axis], BoxSideAtMax(side) ? extra.max_m[axis] : extra.min_m[axis]);
    EXPECT_EQ(after.n_world, BoxSideNormal(side));
    EXPECT_NEAR(DistanceToAabb(after.x_world, extra), 0.0, 1e-12);
    EXPECT_LT(after.t_m, before.t_m - 0.1);
    EXPECT_FALSE(later.Visible(o, p));
    EXPECT_TRUE(later.Visible(o, after.x_world));
    EXPECT_GE(after.albedo_linear.minCoeff(), 0.05f);
    EXPECT_LE(after.albedo_linear.maxCoeff(), 0.95f);
    EXPECT_NEAR(after.reflectance, Luminance(later.Albedo(after.x_world, after.face)), 1e-7);
    std::printf("station (%.1f, %.1f, %.2f): wall at %.3f m, now the extra box (side %d) at "
                "%.3f m, albedo (%.2f, %.2f, %.2f)\n",
                o.x(), o.y(), o.z(), before.t_m, side, after.t_m, after.albedo_linear[0],
                after.albedo_linear[1], after.albedo_linear[2]);
  }
  EXPECT_GE(checked, 2);

  // Rays that miss the extra box are unchanged, bit for bit.
  std::mt19937_64 rng(9);
  std::normal_distribution<double> g(0.0, 1.0);
  size_t changed = 0, on_box = 0;
  for (int k = 0; k < 50000; ++k) {
    const Vector3d o = room.Stations()[k % room.Stations().size()].o_world;
    const Vector3d d = Vector3d(g(rng), g(rng), g(rng)).normalized();
    const SceneHit a = room.Intersect(o, d, kInf);
    const SceneHit b = later.Intersect(o, d, kInf);
    if (b.face >= kFaceCount) {
      ++on_box;
      EXPECT_LT(b.t_m, a.t_m);
      continue;
    }
    changed += a.face != b.face || a.t_m != b.t_m || a.x_world != b.x_world ||
               a.albedo_linear != b.albedo_linear;
  }
  EXPECT_EQ(changed, 0u);
  EXPECT_GT(on_box, 0u);

  // A later scan (station 1, beside the box) sees it; its face can be sampled like the
  // occluder's, and the wall behind it is now shadowed from there.
  LidarSettings lidar;
  lidar.azimuth_steps = 360;
  lidar.elevation_steps = 180;
  const geometry::Pose& s1 = later.Stations()[1];
  const LidarScan scan = GenerateLidar(later, s1, lidar);
  size_t box_points = 0;
  for (size_t k = 0; k < scan.intensity.size(); ++k) {
    const Vector3d x = s1.SensorToWorld(Vector3d(
        scan.xyz_sensor_m[3 * k], scan.xyz_sensor_m[3 * k + 1], scan.xyz_sensor_m[3 * k + 2]));
    box_points += DistanceToAabb(x, extra) < 0.01;
  }
  const auto samples = later.FaceSamples(box_face, 0.1, 0.05, {s1.o_world}, {});
  const auto shadow = later.FaceSamples(kFaceWallYMax, 0.1, 0.05, {}, {s1.o_world});
  const auto old_shadow = room.FaceSamples(kFaceWallYMax, 0.1, 0.05, {}, {s1.o_world});
  std::printf("later scan from station 1: %zu of %zu points on the extra box; %zu face samples "
              "visible on its y-min face; wall y = max shadowed from station 1 at %zu grid "
              "points (before: %zu)\n",
              box_points, scan.intensity.size(), samples.size(), shadow.size(),
              old_shadow.size());
  EXPECT_GT(shadow.size(), old_shadow.size() + 10);
  EXPECT_GT(box_points, 50u);
  EXPECT_GT(samples.size(), 10u);
  for (const Vector3d& p : samples) EXPECT_EQ(p.y(), extra.min_m.y());
}

}  // namespace
}  // namespace vasl::scenes

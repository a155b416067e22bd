/// @file random_site.h
/// @brief A seeded random synthetic site with analytic ground truth: a room of random size and
///        placement holding solid boxes of random size and orientation, scanned from stations
///        at random places with tilted sensors. For property tests of the flows on sites nobody
///        laid out by hand (the room and the corridor are axis-aligned and level).
/// @details Geometry (world frame of VASL-MODEL §2: right-handed, z up, metres): the free space
///          is the inside of an axis-aligned room box (its corner placed off the lattice's grid)
///          minus a set of solid oriented boxes: some stand on the floor, some float, some are
///          thinner than a 5 cm vossel (a plate), and they may cross each other or a wall.
///          Intersect is "leave the room or enter the nearest box", each an exact slab
///          computation (an oriented box in its own frame), so Visible (Scene::Visible) agrees.
///
///          Face ids: 0–5 the room's faces (kBoxSide* order, facing inward); box b has ids
///          6 + 6·b + side (kBoxSide* of its own frame, facing outward).
///
///          Stations: each ≥ kClearanceM from every box and wall, its camera
///          (CameraPoseForStation) too, yawed at random and tilted by up to kMaxTiltRad about a
///          random horizontal axis (a scanner on an uneven tripod, a handheld rig).
/// @warning Immutable after construction: every method is thread-safe. The same seed gives the
///          same site on every machine (the generator is a fixed-width integer recurrence, not a
///          standard-library distribution).
#pragma once

#include <cstdint>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "lattice/geometry/pose.h"
#include "tests/scenes/synthetic_scene.h"

namespace vasl::scenes {

/// One solid box of a RandomSite, in its own frame: x_world = centre + R·x_box, |x_box[a]| ≤
/// half[a].
struct OrientedBox {
  Eigen::Vector3d centre_m = Eigen::Vector3d::Zero();
  Eigen::Vector3d half_m = Eigen::Vector3d::Zero();
  Eigen::Matrix3d R_world_box = Eigen::Matrix3d::Identity();

  /// Distance from a world point to the box (0 inside or on it), metres.
  double DistanceTo(const Eigen::Vector3d& x_world) const;
};

class RandomSite final : public Scene {
 public:
  static constexpr double kClearanceM = 0.45;          ///< station to any surface
  static constexpr double kMaxTiltRad = 25.0 * M_PI / 180.0;

  /// The site of `seed`: `boxes` solid boxes and `stations` stations (each placed by rejection
  /// sampling; a seed whose room cannot hold them all gets as many as fit in 10⁴ draws, so a
  /// caller checks Stations().size()). `outdoor`: a yard of 30-60 m × 20-40 m with walls
  /// 3-6 m high and no ceiling (a ray to the sky hits nothing; the far walls may lie beyond a
  /// scanner's range), boxes 0.5-8 m a side (buildings, containers, sheds).
  RandomSite(uint64_t seed, int boxes, int stations, bool outdoor = false);

  SceneHit Intersect(const Eigen::Vector3d& o_world, const Eigen::Vector3d& d_unit,
                     double t_max_m) const override;
  Aabb Bounds() const override { return room_; }
  const std::vector<geometry::Pose>& Stations() const override { return stations_; }
  const std::vector<geometry::Pose>& NovelViews() const override { return novel_views_; }
  /// Smooth per face (a sinusoid field with the face's own phase and colour), each channel in
  /// [0.05, 0.95].
  Eigen::Vector3f Albedo(const Eigen::Vector3d& x_world, int face) const override;

  const std::vector<OrientedBox>& Boxes() const { return boxes_; }

 private:
  /// Distance from a point to the nearest surface (the room's walls, any box), metres.
  double Clearance(const Eigen::Vector3d& x_world) const;

  Aabb room_;
  bool open_sky_ = false;
  std::vector<OrientedBox> boxes_;
  std::vector<geometry::Pose> stations_;
  std::vector<geometry::Pose> novel_views_;
};

}  // namespace vasl::scenes

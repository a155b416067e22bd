/// @file corridor_site.h
/// @brief A multi-room synthetic site with analytic ground truth: a row of rooms along +x joined
///        by door openings, with thin, horizontal, tall and large occluders and both smooth and
///        sharp-edged (striped, checkered) albedos; 3 stations per room.
/// @details Geometry (world frame of VASL-MODEL §2: right-handed, z up, metres, floor z = 0):
///          the site's free space is the inside of an "envelope" box (floor, ceiling, two end
///          walls, two long walls, all of zero thickness) minus a set of solid axis-aligned boxes
///          ("solids"): the partition walls between rooms (each split into the pieces around its
///          door: two full-height pieces and a lintel above the opening) and the furniture of
///          every room. Intersect is therefore "leave the envelope or enter the nearest solid",
///          both exact slab computations, and Visible (Scene::Visible) follows from it, so the
///          two agree exactly.
///
///          Face ids: 0–5 are the envelope's faces (kCorridorFace*, facing inward); solid b has
///          ids SolidFace(b, side) = kCorridorFirstSolidFace + 6·b + side (kBoxSide*, facing
///          outward).
///
///          Layout of CorridorSite::Default() (documented in full in the .cc): 4 rooms of
///          5 m × 4 m × 3 m, partition walls 0.12 m thick, doors 1.0 m wide × 2.1 m tall,
///          alternately at y ∈ [1, 2] and [2, 3] (staggered); per room a table (0.02 m top at
///          0.75 m on four 0.05 m legs), a 0.25 m × 0.25 m × 2.5 m pillar and a large box; odd
///          rooms are the even rooms mirrored in y. Site x ∈ [0, 20.36].
/// @warning Immutable after construction: every method is thread-safe.
#pragma once

#include <string>
#include <vector>

#include <Eigen/Core>

#include "lattice/geometry/pose.h"
#include "tests/scenes/synthetic_scene.h"

namespace vasl::scenes {

/// Envelope face ids of a CorridorSite (facing into the site's free space).
inline constexpr int kCorridorFaceFloor = 0;     ///< z = min
inline constexpr int kCorridorFaceCeiling = 1;   ///< z = max
inline constexpr int kCorridorFaceEndXMin = 2;   ///< x = min: the first room's end wall
inline constexpr int kCorridorFaceEndXMax = 3;   ///< x = max: the last room's end wall
inline constexpr int kCorridorFaceLongYMin = 4;  ///< y = min: long wall (smooth albedo)
inline constexpr int kCorridorFaceLongYMax = 5;  ///< y = max: long wall (striped albedo)
inline constexpr int kCorridorFirstSolidFace = 6;  ///< face id of side 0 of solid 0

/// What a solid of the corridor site is (it selects the solid's albedo).
enum class SolidKind {
  kWall,      ///< a full-height piece of a partition wall beside a door
  kLintel,    ///< the piece of a partition wall above a door
  kTableTop,  ///< a thin horizontal table top (striped, planks)
  kTableLeg,  ///< a table leg (smooth dark)
  kPillar,    ///< a tall narrow pillar (horizontal stripes)
  kBox,       ///< a large box standing on the floor (checkered)
};

/// One solid axis-aligned box of the site.
struct CorridorSolid {
  Aabb box;                         ///< world, metres
  SolidKind kind = SolidKind::kBox; ///< what it is
  int room = 0;                     ///< room it stands in; walls: the room on its x-min side
};

/// A door opening: the hole through a partition wall between two neighbouring rooms.
struct CorridorDoor {
  Aabb opening;      ///< the hole, world, metres (x across the wall's thickness)
  int room_xmin = 0; ///< index of the room on the opening's x-min side
  int room_xmax = 1; ///< index of the room on its x-max side (room_xmin + 1)
};

/// A row of rooms along +x joined by doors; see the file comment.
class CorridorSite final : public Scene {
 public:
  /// The canonical corridor site: 4 rooms, 12 stations (3 per room), 4 novel views.
  static CorridorSite Default();

  /// First hit of the ray o + t·d, 0 < t ≤ t_max_m; `d_unit` unit length, `o_world` in free
  /// space (a solid containing the origin is skipped, as are envelope faces behind it).
  SceneHit Intersect(const Eigen::Vector3d& o_world, const Eigen::Vector3d& d_unit,
                     double t_max_m) const override;

  /// The envelope: the site's free space and every solid lie inside it, world, metres.
  Aabb Bounds() const override { return envelope_; }

  /// 3 stations per room, in room order (stations 3i, 3i+1, 3i+2 stand in room i), 1.2–1.7 m
  /// above the floor, yawed differently, ≥ 0.8 m from walls and solids.
  const std::vector<geometry::Pose>& Stations() const override { return stations_; }

  /// One viewpoint per room, ≥ 0.5 m from every station and camera, ≥ 0.3 m from solids.
  const std::vector<geometry::Pose>& NovelViews() const override { return novel_views_; }

  /// Linear RGB albedo of x on face `face`, each channel in [0.05, 0.95]. Envelope faces take
  /// the colours of the room x lies in. Smooth (wavelengths ≥ 1.4 m): ceiling, end walls, long
  /// wall y = min, partition faces, table legs and edges, pillar top. Sharp-edged: floor
  /// (checker, 0.4 m period), long wall y = max (stripes, 0.3 m period along x in even rooms,
  /// 0.25 m along z in odd rooms), table top (stripes 0.2 m along x), pillar sides (stripes
  /// 0.35 m along z), large boxes (checker, 0.3 m). Unknown ids give 0.05.
  Eigen::Vector3f Albedo(const Eigen::Vector3d& x_world, int face) const override;

  /// Number of rooms.
  int RoomCount() const { return static_cast<int>(rooms_.size()); }
  /// Free space of room i (from partition face to partition face), world, metres.
  const Aabb& RoomInterior(int i) const { return rooms_.at(i); }
  /// Index of the room whose interior holds x (boundaries included), −1 if none (e.g. inside
  /// a partition wall or a door opening).
  int RoomAt(const Eigen::Vector3d& x_world) const;
  /// Room a station stands in.
  int StationRoom(size_t station) const { return static_cast<int>(station / 3); }

  /// Every solid, world, metres; solid b owns face ids SolidFace(b, side).
  const std::vector<CorridorSolid>& Solids() const { return solids_; }
  /// Door openings, one per partition wall, in x order.
  const std::vector<CorridorDoor>& Doors() const { return doors_; }

  /// Face id of side `side` (kBoxSide*) of solid b.
  static int SolidFace(size_t b, int side) {
    return kCorridorFirstSolidFace + kBoxSideCount * static_cast<int>(b) + side;
  }
  /// Solid index of a face id, −1 for envelope faces and kFaceNone.
  static int SolidOfFace(int face) {
    return face < kCorridorFirstSolidFace ? -1 : (face - kCorridorFirstSolidFace) / kBoxSideCount;
  }
  /// Unit normal of a face, pointing into free space (envelope inward, solids outward).
  static Eigen::Vector3d FaceNormal(int face);

  /// Name of a solid kind ("wall", "lintel", "table_top", "table_leg", "pillar", "box").
  static std::string KindName(SolidKind kind);

 private:
  /// A contiguous range of solids_ with their union box, for culling rays: the furniture of
  /// one room, or the pieces of one partition wall.
  struct SolidGroup {
    Aabb bounds;     ///< union of the members' boxes, world, metres
    int first = 0;   ///< index of the first member in solids_
    int count = 0;   ///< number of members
  };

  /// Most groups a site may have (Intersect keeps its candidates on the stack).
  static constexpr int kMaxGroups = 32;

  Aabb envelope_;                            ///< the site's outer free-space box
  std::vector<Aabb> rooms_;                  ///< room interiors, in x order
  std::vector<CorridorSolid> solids_;        ///< walls and furniture
  std::vector<CorridorDoor> doors_;          ///< door openings, in x order
  std::vector<SolidGroup> groups_;           ///< culling groups, partitioning solids_
  std::vector<geometry::Pose> stations_;     ///< T_world_scanner, 3 per room
  std::vector<geometry::Pose> novel_views_;  ///< render-test viewpoints
};

}  // namespace vasl::scenes

/// @file embree_peer.h
/// @brief The peer of the render benchmark (issue "Speed"): Embree tracing the same scene as
///        triangles, with the same equirect rays, on the same threads as vasl's render.
/// @details Two meshes of one site: the synthetic site's own solids (every box of the analytic
///          scene as 12 triangles: what a modeller would hand Embree) and the stored lattice's
///          surface (each vossel with a normal as a square surfel of 2 triangles, side
///          `surfel_scale`·h, centred on its centroid in its tangent plane: the same data vasl
///          marches). Rays are §2.1's equirect pixel centres turned into the world by the pose,
///          one per pixel, traced with `rtcIntersect1` per ray or `rtcIntersect8` per packet of 8
///          neighbouring pixels of a row, rows spread over TBB's threads as the render's are.
///          Built only where Debian's libembree-dev is installed (deploy/bench.sh installs it).
#pragma once

#include <cstdint>
#include <vector>

#include <Eigen/Core>

#include "lattice/geometry/pose.h"
#include "lattice/records/records.h"
#include "tests/scenes/synthetic_scene.h"

namespace vasl::bench {

/// An indexed triangle mesh, world metres, for Embree (float3 vertices, uint3 triangles).
struct TriangleMesh {
  std::vector<float> xyz;           ///< 3 per vertex
  std::vector<uint32_t> triangles;  ///< 3 vertex indices per triangle
  size_t TriangleCount() const { return triangles.size() / 3; }
};

/// Every box as 12 triangles (two per side); Embree does not cull back faces, so one mesh
/// serves boxes seen from inside (a site's envelope) and from outside (its solids).
TriangleMesh BoxesAsTriangles(const std::vector<scenes::Aabb>& boxes);

/// Each vossel with a non-zero normal as a square of side surfel_scale·h centred on its
/// centroid, in the plane normal to its normal (2 triangles, 4 vertices).
TriangleMesh SurfelsAsTriangles(const records::VosselGeometry& geometry, double surfel_scale);

/// One traced equirect image: per pixel the hit distance (+inf: none), and the rate.
struct PeerTrace {
  std::vector<float> depth_m;  ///< W·H, row-major, metres along the unit ray
  int64_t hit_pixels = 0;
  double seconds = 0.0;        ///< tracing alone (scene built before), rays generated inside
};

/// A scene built once (BVH), traced many times.
class EmbreeScene {
 public:
  explicit EmbreeScene(const TriangleMesh& mesh);
  ~EmbreeScene();
  EmbreeScene(const EmbreeScene&) = delete;
  EmbreeScene& operator=(const EmbreeScene&) = delete;

  /// Seconds the BVH took to build.
  double build_seconds() const { return build_seconds_; }

  /// Traces a W×H equirect image from `pose` (T_world_camera), rays to max_range_m, with
  /// packets of `packet` rays (1 or 8), rows in parallel on TBB's threads.
  PeerTrace TraceEquirect(const geometry::Pose& pose, int width_px, int height_px, int packet,
                          double max_range_m) const;

 private:
  struct Impl;
  Impl* impl_ = nullptr;
  double build_seconds_ = 0.0;
};

}  // namespace vasl::bench

#include "tests/bench/embree_peer.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <limits>

#include <embree3/rtcore.h>
#include <tbb/blocked_range.h>
#include <tbb/combinable.h>
#include <tbb/parallel_for.h>

#include <Eigen/Geometry>

#include "lattice/geometry/equirect.h"

namespace vasl::bench {
namespace {

using Clock = std::chrono::steady_clock;

void AddQuad(TriangleMesh& mesh, const std::array<Eigen::Vector3f, 4>& corners) {
  const auto first = static_cast<uint32_t>(mesh.xyz.size() / 3);
  for (const Eigen::Vector3f& c : corners) mesh.xyz.insert(mesh.xyz.end(), {c.x(), c.y(), c.z()});
  mesh.triangles.insert(mesh.triangles.end(),
                        {first, first + 1, first + 2, first, first + 2, first + 3});
}

}  // namespace

TriangleMesh BoxesAsTriangles(const std::vector<scenes::Aabb>& boxes) {
  TriangleMesh mesh;
  for (const scenes::Aabb& b : boxes) {
    const Eigen::Vector3f lo = b.min_m.cast<float>(), hi = b.max_m.cast<float>();
    for (int side = 0; side < scenes::kBoxSideCount; ++side) {
      // The side's plane fixes axis a at lo or hi; its corners run around the other two axes.
      const int a = scenes::BoxSideAxis(side), u = (a + 1) % 3, v = (a + 2) % 3;
      std::array<Eigen::Vector3f, 4> c;
      for (int k = 0; k < 4; ++k) {
        c[k][a] = scenes::BoxSideAtMax(side) ? hi[a] : lo[a];
        c[k][u] = (k == 1 || k == 2) ? hi[u] : lo[u];
        c[k][v] = (k >= 2) ? hi[v] : lo[v];
      }
      AddQuad(mesh, c);
    }
  }
  return mesh;
}

TriangleMesh SurfelsAsTriangles(const records::VosselGeometry& geometry, double surfel_scale) {
  TriangleMesh mesh;
  const float half = float(0.5 * surfel_scale * geometry.vossel_size_m);
  for (size_t k = 0; k < geometry.normal.size(); ++k) {
    const Eigen::Vector3f& n = geometry.normal[k];
    if (n.squaredNorm() == 0.0f) continue;
    // A tangent basis (t, b) of the normal's plane.
    const Eigen::Vector3f t =
        (std::abs(n.x()) < 0.9f ? Eigen::Vector3f::UnitX() : Eigen::Vector3f::UnitY())
            .cross(n)
            .normalized();
    const Eigen::Vector3f b = n.cross(t);
    const Eigen::Vector3f& c = geometry.centroid_m[k];
    AddQuad(mesh, {c - half * t - half * b, c + half * t - half * b, c + half * t + half * b,
                   c - half * t + half * b});
  }
  return mesh;
}

struct EmbreeScene::Impl {
  RTCDevice device = nullptr;
  RTCScene scene = nullptr;
};

EmbreeScene::EmbreeScene(const TriangleMesh& mesh) : impl_(new Impl) {
  const auto t0 = Clock::now();
  impl_->device = rtcNewDevice(nullptr);
  impl_->scene = rtcNewScene(impl_->device);
  RTCGeometry g = rtcNewGeometry(impl_->device, RTC_GEOMETRY_TYPE_TRIANGLE);
  const size_t vertices = mesh.xyz.size() / 3;
  auto* v = static_cast<float*>(rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0,
                                                        RTC_FORMAT_FLOAT3, 3 * sizeof(float),
                                                        vertices));
  std::copy(mesh.xyz.begin(), mesh.xyz.end(), v);
  auto* t = static_cast<uint32_t*>(rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_INDEX, 0,
                                                           RTC_FORMAT_UINT3, 3 * sizeof(uint32_t),
                                                           mesh.TriangleCount()));
  std::copy(mesh.triangles.begin(), mesh.triangles.end(), t);
  rtcCommitGeometry(g);
  rtcAttachGeometry(impl_->scene, g);
  rtcReleaseGeometry(g);
  rtcCommitScene(impl_->scene);
  build_seconds_ = std::chrono::duration<double>(Clock::now() - t0).count();
}

EmbreeScene::~EmbreeScene() {
  rtcReleaseScene(impl_->scene);
  rtcReleaseDevice(impl_->device);
  delete impl_;
}

PeerTrace EmbreeScene::TraceEquirect(const geometry::Pose& pose, int width_px, int height_px,
                                     int packet, double max_range_m) const {
  PeerTrace out;
  out.depth_m.assign(size_t(width_px) * height_px, std::numeric_limits<float>::infinity());
  const auto t0 = Clock::now();
  // §2.1's pixel-centre directions, as EquirectUnproject gives them: azimuth per column (a
  // table shared by the rows), elevation per row, turned into the world by the pose.
  const geometry::EquirectSize size{width_px, height_px};
  std::vector<double> cos_phi(width_px), sin_phi(width_px);
  for (int i = 0; i < width_px; ++i) {
    const double phi = geometry::EquirectAzimuthRad(i + 0.5, size);
    cos_phi[i] = std::cos(phi);
    sin_phi[i] = std::sin(phi);
  }
  const Eigen::Matrix3d r = pose.q_world_sensor.toRotationMatrix();
  const Eigen::Vector3f o = pose.o_world.cast<float>();
  const float t_far = float(max_range_m);
  RTCScene scene = impl_->scene;
  tbb::combinable<int64_t> hits([] { return int64_t{0}; });
  tbb::parallel_for(tbb::blocked_range<int>(0, height_px), [&](const tbb::blocked_range<int>& rows) {
    RTCIntersectContext context;
    rtcInitIntersectContext(&context);
    context.flags = RTC_INTERSECT_CONTEXT_FLAG_COHERENT;  // the rays of a row are
    int64_t& hit_count = hits.local();
    for (int j = rows.begin(); j < rows.end(); ++j) {
      const double psi = geometry::EquirectElevationRad(j + 0.5, size);
      const double cos_psi = std::cos(psi), sin_psi = std::sin(psi);
      float* depth = out.depth_m.data() + size_t(j) * width_px;
      auto direction = [&](int i) {
        return (r * geometry::EquirectDirection(cos_phi[i], sin_phi[i], cos_psi, sin_psi))
            .cast<float>()
            .eval();
      };
      if (packet == 1) {
        for (int i = 0; i < width_px; ++i) {
          const Eigen::Vector3f d = direction(i);
          RTCRayHit rh;
          rh.ray.org_x = o.x(); rh.ray.org_y = o.y(); rh.ray.org_z = o.z();
          rh.ray.dir_x = d.x(); rh.ray.dir_y = d.y(); rh.ray.dir_z = d.z();
          rh.ray.tnear = 0.0f;
          rh.ray.tfar = t_far;
          rh.ray.mask = ~0u;
          rh.ray.flags = 0;
          rh.ray.time = 0.0f;
          rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
          rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
          rtcIntersect1(scene, &context, &rh);
          if (rh.hit.geomID != RTC_INVALID_GEOMETRY_ID) {
            depth[i] = rh.ray.tfar;
            ++hit_count;
          }
        }
        continue;
      }
      for (int i0 = 0; i0 < width_px; i0 += 8) {
        alignas(32) int valid[8];
        alignas(32) RTCRayHit8 rh;
        for (int l = 0; l < 8; ++l) {
          const int i = i0 + l;
          valid[l] = i < width_px ? -1 : 0;
          const Eigen::Vector3f d = direction(std::min(i, width_px - 1));
          rh.ray.org_x[l] = o.x(); rh.ray.org_y[l] = o.y(); rh.ray.org_z[l] = o.z();
          rh.ray.dir_x[l] = d.x(); rh.ray.dir_y[l] = d.y(); rh.ray.dir_z[l] = d.z();
          rh.ray.tnear[l] = 0.0f;
          rh.ray.tfar[l] = t_far;
          rh.ray.mask[l] = ~0u;
          rh.ray.flags[l] = 0;
          rh.ray.time[l] = 0.0f;
          rh.hit.geomID[l] = RTC_INVALID_GEOMETRY_ID;
          rh.hit.instID[0][l] = RTC_INVALID_GEOMETRY_ID;
        }
        rtcIntersect8(valid, scene, &context, &rh);
        for (int l = 0; l < 8 && i0 + l < width_px; ++l) {
          if (rh.hit.geomID[l] != RTC_INVALID_GEOMETRY_ID) {
            depth[i0 + l] = rh.ray.tfar[l];
            ++hit_count;
          }
        }
      }
    }
  });
  out.seconds = std::chrono::duration<double>(Clock::now() - t0).count();
  out.hit_pixels = hits.combine(std::plus<int64_t>());
  return out;
}

}  // namespace vasl::bench

#include "lattice/ingest/voxelise.h"

#include <algorithm>
#include <cmath>

#include <Eigen/Eigenvalues>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_sort.h>

#include "absl/strings/str_cat.h"
#include "lattice/records/record_grid.h"

namespace vasl::ingest {
namespace {

constexpr int kKeyBits = 21;
constexpr uint64_t kNoKey = ~uint64_t(0);  // skipped returns: sorts after every vossel
constexpr int64_t kKeyOffset = int64_t(1) << (kKeyBits - 1);

uint64_t PackKey(const openvdb::Coord& c) {
  return (uint64_t(c.x() + kKeyOffset) << (2 * kKeyBits)) |
         (uint64_t(c.y() + kKeyOffset) << kKeyBits) | uint64_t(c.z() + kKeyOffset);
}
openvdb::Coord UnpackKey(uint64_t key) {
  const uint64_t mask = (uint64_t(1) << kKeyBits) - 1;
  return openvdb::Coord(int(int64_t((key >> (2 * kKeyBits)) & mask) - kKeyOffset),
                        int(int64_t((key >> kKeyBits) & mask) - kKeyOffset),
                        int(int64_t(key & mask) - kKeyOffset));
}

struct KeyedPoint {
  uint64_t key;
  uint32_t lidar;  // index into the lidars vector
  uint32_t point;  // point index in that lidar
  bool operator<(const KeyedPoint& o) const {
    return key != o.key ? key < o.key : (lidar != o.lidar ? lidar < o.lidar : point < o.point);
  }
};

}  // namespace

absl::StatusOr<records::VosselGeometry> BuildGeometry(const std::vector<LidarSource>& lidars,
                                                      double h) {
  // 1. Every return to world, keyed by its vossel (cell-centred: k = round(x / h), §1).
  size_t total = 0;
  std::vector<size_t> first(lidars.size() + 1, 0);
  for (size_t s = 0; s < lidars.size(); ++s) first[s + 1] = first[s] + lidars[s].point_count();
  total = first.back();
  std::vector<KeyedPoint> keyed(total);
  std::vector<Eigen::Vector3f> x_world(total);
  std::atomic<bool> out_of_range{false};
  for (size_t s = 0; s < lidars.size(); ++s) {
    const LidarSource& src = lidars[s];
    const Eigen::Matrix3f R = src.pose.q_world_sensor.toRotationMatrix().cast<float>();
    const Eigen::Vector3f o = src.pose.o_world.cast<float>();
    tbb::parallel_for(tbb::blocked_range<size_t>(0, src.point_count(), 1 << 14),
                      [&](const tbb::blocked_range<size_t>& r) {
      for (size_t i = r.begin(); i != r.end(); ++i) {
        const Eigen::Vector3f p(&src.xyz_sensor_m[3 * i]);
        const size_t g = first[s] + i;
        if (p.x() == 0.0f && p.y() == 0.0f && p.z() == 0.0f) {  // "no return" marker
          keyed[g] = {kNoKey, uint32_t(s), uint32_t(i)};
          continue;
        }
        const Eigen::Vector3f x = R * p + o;
        x_world[g] = x;
        const Eigen::Vector3d k = VosselIndexOf(x, h);
        if (k.cwiseAbs().maxCoeff() > kMaxVosselIndex) {
          out_of_range = true;
          keyed[g] = {kNoKey, uint32_t(s), uint32_t(i)};
          continue;
        }
        keyed[g] = {PackKey(openvdb::Coord(int(k.x()), int(k.y()), int(k.z()))), uint32_t(s), uint32_t(i)};
      }
    });
  }
  if (out_of_range) {
    return absl::InvalidArgumentError(absl::StrCat(
        "a point lies farther than ", kMaxVosselIndex * h,
        " m from the world origin on some axis, outside the lattice; check the pose and units"));
  }
  tbb::parallel_sort(keyed.begin(), keyed.end());

  // 2. Group runs of equal keys into vossels; skipped returns sort last.
  size_t end = 0;
  while (end < total && keyed[end].key != kNoKey) ++end;
  std::vector<size_t> run_begin;
  for (size_t i = 0; i < end; ++i) {
    if (i == 0 || keyed[i].key != keyed[i - 1].key) run_begin.push_back(i);
  }
  const size_t nv = run_begin.size();
  run_begin.push_back(end);
  records::VosselGeometry g;
  g.vossel_size_m = h;
  g.coord.resize(nv);
  g.point_count.resize(nv);
  g.centroid_m.resize(nv);
  g.covariance_m2.resize(nv);
  std::vector<Eigen::Vector3f> view_sum(nv);
  std::vector<Eigen::Vector3f> origins;
  for (const LidarSource& src : lidars) origins.push_back(src.pose.o_world.cast<float>());
  tbb::parallel_for(tbb::blocked_range<size_t>(0, nv, 4096), [&](const tbb::blocked_range<size_t>& r) {
    for (size_t v = r.begin(); v != r.end(); ++v) {
      const size_t b = run_begin[v], e = run_begin[v + 1];
      Eigen::Vector3d mean = Eigen::Vector3d::Zero();
      Eigen::Vector3f view = Eigen::Vector3f::Zero();
      for (size_t i = b; i < e; ++i) {
        const Eigen::Vector3f& x = x_world[first[keyed[i].lidar] + keyed[i].point];
        mean += x.cast<double>();
        view += (origins[keyed[i].lidar] - x).normalized();
      }
      mean /= double(e - b);
      Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
      for (size_t i = b; i < e; ++i) {
        const Eigen::Vector3d d = x_world[first[keyed[i].lidar] + keyed[i].point].cast<double>() - mean;
        cov += d * d.transpose();
      }
      cov /= double(e - b);
      g.coord[v] = UnpackKey(keyed[b].key);
      g.point_count[v] = int32_t(e - b);
      g.centroid_m[v] = mean.cast<float>();
      g.covariance_m2[v] = {float(cov(0, 0)), float(cov(0, 1)), float(cov(0, 2)),
                            float(cov(1, 1)), float(cov(1, 2)), float(cov(2, 2))};
      view_sum[v] = view;
    }
  });

  // 3. Canonical order (the PointDataGrid's), then normals.
  const std::vector<int32_t> old_to_new = records::CanonicalizeVosselOrder(g);
  std::vector<Eigen::Vector3f> view_sorted(nv);
  for (size_t v = 0; v < nv; ++v) view_sorted[size_t(old_to_new[v])] = view_sum[v];
  ComputeNormals(g, view_sorted);
  return g;
}

void ComputeNormals(records::VosselGeometry& g, const std::vector<Eigen::Vector3f>& view_sum) {
  const size_t nv = g.size();
  g.normal.assign(nv, Eigen::Vector3f::Zero());
  if (nv == 0) return;
  const openvdb::Int32Grid& index = *g.index_grid;
  tbb::parallel_for(tbb::blocked_range<size_t>(0, nv, 2048), [&](const tbb::blocked_range<size_t>& r) {
    auto acc = index.getConstAccessor();
    for (size_t v = r.begin(); v != r.end(); ++v) {
      // Pooled scatter of the points of the 3×3×3 neighbourhood: Σ_j c_j (Σ_j + (μ_j − μ)(μ_j − μ)ᵀ).
      double total = 0.0;
      Eigen::Vector3d mean = Eigen::Vector3d::Zero();
      int neighbours = 0;
      int32_t ids[27];
      const openvdb::Coord c = g.coord[v];
      for (int dx = -1; dx <= 1; ++dx)
        for (int dy = -1; dy <= 1; ++dy)
          for (int dz = -1; dz <= 1; ++dz) {
            int32_t id;
            if (acc.probeValue(c.offsetBy(dx, dy, dz), id)) {
              ids[neighbours++] = id;
              total += g.point_count[id];
              mean += double(g.point_count[id]) * g.centroid_m[id].cast<double>();
            }
          }
      mean /= total;
      Eigen::Matrix3d scatter = Eigen::Matrix3d::Zero();
      for (int j = 0; j < neighbours; ++j) {
        const auto& s = g.covariance_m2[ids[j]];
        Eigen::Matrix3d cov;
        cov << s[0], s[1], s[2], s[1], s[3], s[4], s[2], s[4], s[5];
        const Eigen::Vector3d d = g.centroid_m[ids[j]].cast<double>() - mean;
        scatter += double(g.point_count[ids[j]]) * (cov + d * d.transpose());
      }
      Eigen::Vector3f view = view_sum.empty() ? Eigen::Vector3f::Zero() : view_sum[v];
      Eigen::Vector3f n = Eigen::Vector3f::Zero();
      if (total >= 3.0) {
        Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(scatter);
        const Eigen::Vector3d ev = eig.eigenvalues();  // ascending
        if (ev[1] > 1e-12 * std::max(1.0, ev[2])) n = eig.eigenvectors().col(0).cast<float>();
      }
      if (n.squaredNorm() == 0.0f) n = view;  // no plane: face the sensors
      if (n.squaredNorm() > 0.0f) {
        n.normalize();
        if (n.dot(view) < 0.0f) n = -n;
      }
      g.normal[v] = n;
    }
  });
}

}  // namespace vasl::ingest

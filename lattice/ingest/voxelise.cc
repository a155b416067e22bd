#include "lattice/ingest/voxelise.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>

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
constexpr uint32_t kNoGridPoint = ~uint32_t(0);

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
  uint32_t point;  // point index in the LiDAR; from point_count() on, a gap-fill point
  bool operator<(const KeyedPoint& o) const { return key != o.key ? key < o.key : point < o.point; }
};

// Surface connectivity from a scan's range grid (voxelise.h, GapFill): the points of the
// triangles between grid-neighbouring returns on one surface that fall in vossels holding none
// of the scan's returns, in grid order (so that their sums do not depend on the thread count).
// `real` holds the returns' keys, sorted, the first `real_end` of them valid.
GapFillPoints FillGaps(const LidarSource& src, double h, const Eigen::Matrix3d& R,
                       const Eigen::Vector3d& o, const std::vector<KeyedPoint>& real,
                       size_t real_end) {
  const uint64_t rows = uint64_t(src.grid_rows), cols = uint64_t(src.grid_columns);
  // The returns by cell (memory grows with the returns, not the grid): a cell given twice
  // keeps its last return.
  std::vector<std::pair<uint32_t, uint32_t>> by_cell;  // (cell, return)
  for (size_t i = 0; i < src.grid_cell.size(); ++i) {
    const float* p = &src.xyz_sensor_m[3 * i];
    if (p[0] == 0.0f && p[1] == 0.0f && p[2] == 0.0f) continue;
    by_cell.emplace_back(src.grid_cell[i], uint32_t(i));
  }
  tbb::parallel_sort(by_cell.begin(), by_cell.end());
  const auto at = [&](uint64_t cell) {
    const auto it = std::upper_bound(by_cell.begin(), by_cell.end(),
                                     std::make_pair(uint32_t(cell), kNoGridPoint));
    return it != by_cell.begin() && std::prev(it)->first == cell ? std::prev(it)->second
                                                                 : kNoGridPoint;
  };
  // The quads with a return at a corner, by their top-left cell (grid order).
  std::vector<uint32_t> quads;
  quads.reserve(4 * by_cell.size());
  for (const auto& [cell, point] : by_cell) {
    const uint64_t r = cell / cols, c = cell % cols;
    for (uint64_t dr = 0; dr <= std::min<uint64_t>(r, 1); ++dr)
      for (uint64_t dc = 0; dc <= std::min<uint64_t>(c, 1); ++dc)
        if (r - dr + 1 < rows && c - dc + 1 < cols) quads.push_back(uint32_t(cell - dr * cols - dc));
  }
  tbb::parallel_sort(quads.begin(), quads.end());
  quads.erase(std::unique(quads.begin(), quads.end()), quads.end());
  const auto holds_return = [&](uint64_t key) {
    const auto it = std::lower_bound(real.begin(), real.begin() + ptrdiff_t(real_end),
                                     KeyedPoint{key, 0});
    return it != real.begin() + ptrdiff_t(real_end) && it->key == key;
  };
  const double max_edge = kGapFillMaxEdgeVossels * h, step = kGapFillStepVossels * h;
  constexpr size_t kBlock = 4096;  // quads a task takes; outputs joined in block order
  std::vector<GapFillPoints> per_block((quads.size() + kBlock - 1) / kBlock);
  tbb::parallel_for(size_t{0}, per_block.size(), [&](size_t block) {
    GapFillPoints& out = per_block[block];
    for (size_t q = block * kBlock; q < std::min(quads.size(), (block + 1) * kBlock); ++q) {
      const uint64_t tl = quads[q];
      const uint32_t id[4] = {at(tl), at(tl + 1), at(tl + cols + 1), at(tl + cols)};
      // The quad's two triangles, or the one its three returns make when a corner has none.
      const int valid = (id[0] != kNoGridPoint) + (id[1] != kNoGridPoint) +
                        (id[2] != kNoGridPoint) + (id[3] != kNoGridPoint);
      if (valid < 3) continue;
      Eigen::Vector3d x[4];
      double range[4] = {0, 0, 0, 0};
      for (int k = 0; k < 4; ++k) {
        if (id[k] == kNoGridPoint) continue;
        const float* p = &src.xyz_sensor_m[3 * size_t(id[k])];
        range[k] = Eigen::Vector3d(p[0], p[1], p[2]).norm();
        x[k] = ReturnPosition(R, o, p);
      }
      int tri[2][3] = {{0, 1, 2}, {0, 2, 3}};
      int n_tri = 2;
      if (valid == 3) {
        int k = 0;
        for (int j = 0; j < 4; ++j)
          if (id[j] != kNoGridPoint) tri[0][k++] = j;
        n_tri = 1;
      }
      for (int t = 0; t < n_tri; ++t) {
        const int a = tri[t][0], b = tri[t][1], d = tri[t][2];
        const double lo = std::min({range[a], range[b], range[d]});
        const double hi = std::max({range[a], range[b], range[d]});
        if (hi > lo * (1.0 + kGapFillRangeStep)) continue;  // a depth edge: two surfaces
        const double edge = std::max({(x[a] - x[b]).norm(), (x[b] - x[d]).norm(),
                                      (x[d] - x[a]).norm()});
        if (edge <= h || edge > max_edge) continue;  // no gap, or too wide to bridge
        const int n = int(std::ceil(edge / step));
        for (int i = 0; i <= n; ++i)
          for (int j = 0; i + j <= n; ++j) {
            if ((i == 0 && j == 0) || (i == n && j == 0) || (i == 0 && j == n)) continue;
            const double wb = double(i) / n, wd = double(j) / n;
            const Eigen::Vector3d y = x[a] + wb * (x[b] - x[a]) + wd * (x[d] - x[a]);
            const Eigen::Vector3d k = VosselIndexOf(y, h);
            if (k.cwiseAbs().maxCoeff() > kMaxVosselIndex) continue;
            if (holds_return(PackKey(openvdb::Coord(int(k.x()), int(k.y()), int(k.z()))))) continue;
            out.x.push_back(y);
            out.corner.push_back({id[a], id[b], id[d]});
            out.weight.push_back({float(1.0 - wb - wd), float(wb), float(wd)});
          }
      }
    }
  });
  GapFillPoints all;
  for (GapFillPoints& row : per_block) {
    all.x.insert(all.x.end(), row.x.begin(), row.x.end());
    all.corner.insert(all.corner.end(), row.corner.begin(), row.corner.end());
    all.weight.insert(all.weight.end(), row.weight.begin(), row.weight.end());
  }
  return all;
}

// Step 1 of binning: every return keyed by its vossel (cell-centred: k = round(x / h), §1),
// sorted; "no return" markers and points beyond the lattice get kNoKey (sorting last). The
// count of keyed returns; false in `in_range` when a point lies beyond the lattice.
size_t KeyReturns(const LidarSource& src, double h, const Eigen::Matrix3d& R,
                  const Eigen::Vector3d& o, std::vector<KeyedPoint>* keyed, bool* in_range) {
  const size_t total = src.point_count();
  keyed->resize(total);
  std::atomic<bool> out_of_range{false};
  tbb::parallel_for(tbb::blocked_range<size_t>(0, total, 1 << 14),
                    [&](const tbb::blocked_range<size_t>& r) {
    for (size_t i = r.begin(); i != r.end(); ++i) {
      const float* p = &src.xyz_sensor_m[3 * i];
      if (p[0] == 0.0f && p[1] == 0.0f && p[2] == 0.0f) {  // "no return" marker
        (*keyed)[i] = {kNoKey, uint32_t(i)};
        continue;
      }
      const Eigen::Vector3d k = VosselIndexOf(ReturnPosition(R, o, p), h);
      if (k.cwiseAbs().maxCoeff() > kMaxVosselIndex) {
        out_of_range = true;
        (*keyed)[i] = {kNoKey, uint32_t(i)};
        continue;
      }
      (*keyed)[i] = {PackKey(openvdb::Coord(int(k.x()), int(k.y()), int(k.z()))), uint32_t(i)};
    }
  });
  *in_range = !out_of_range;
  tbb::parallel_sort(keyed->begin(), keyed->end());
  size_t end = 0;
  while (end < total && (*keyed)[end].key != kNoKey) ++end;
  return end;
}

}  // namespace

absl::StatusOr<BinnedLidar> BinLidar(const LidarSource& src, double h) {
  // 1. Every return keyed by its vossel (cell-centred: k = round(x / h), §1).
  const size_t total = src.point_count();
  const Eigen::Matrix3d R = src.pose.q_world_sensor.toRotationMatrix();
  const Eigen::Vector3d o = src.pose.o_world;
  std::vector<KeyedPoint> keyed;
  bool in_range = true;
  size_t end = KeyReturns(src, h, R, o, &keyed, &in_range);
  if (!in_range) {
    return absl::InvalidArgumentError(absl::StrCat(
        "a point lies farther than ", kMaxVosselIndex * h,
        " m from the project's origin on some axis, outside the lattice; check the pose and "
        "units"));
  }

  // 2. With a range grid, the gaps between neighbouring returns on one surface are filled
  // (gap-fill points join the returns, numbered after them).
  std::shared_ptr<const GapFillPoints> filled;
  if (src.HasGrid()) {
    filled = std::make_shared<const GapFillPoints>(FillGaps(src, h, R, o, keyed, end));
    if (total + filled->size() > std::numeric_limits<uint32_t>::max()) {
      return absl::InvalidArgumentError("a scan's returns and gap fill exceed 2^32 points");
    }
    for (size_t f = 0; f < filled->size(); ++f) {
      const Eigen::Vector3d k = VosselIndexOf(filled->x[f], h);
      keyed.push_back({PackKey(openvdb::Coord(int(k.x()), int(k.y()), int(k.z()))),
                       uint32_t(total + f)});
    }
    tbb::parallel_sort(keyed.begin(), keyed.end());
    end = 0;
    while (end < keyed.size() && keyed[end].key != kNoKey) ++end;
  }
  const auto position = [&](uint32_t point) {
    return point < total ? ReturnPosition(R, o, &src.xyz_sensor_m[3 * size_t(point)])
                         : filled->x[point - total];
  };

  // 3. Runs of equal keys are vossels; skipped returns sort last. Sums in point order.
  std::vector<size_t> run_begin;
  for (size_t i = 0; i < end; ++i) {
    if (i == 0 || keyed[i].key != keyed[i - 1].key) run_begin.push_back(i);
  }
  const size_t nv = run_begin.size();
  run_begin.push_back(end);
  BinnedLidar out;
  out.fill = filled;
  out.coord.resize(nv);
  out.count.resize(nv);
  out.sums.resize(nv);
  tbb::parallel_for(tbb::blocked_range<size_t>(0, nv, 4096), [&](const tbb::blocked_range<size_t>& r) {
    for (size_t v = r.begin(); v != r.end(); ++v) {
      const size_t b = run_begin[v], e = run_begin[v + 1];
      const openvdb::Coord k = UnpackKey(keyed[b].key);
      const Eigen::Vector3d centre = h * Eigen::Vector3d(k.x(), k.y(), k.z());
      records::VosselSums s;
      for (size_t i = b; i < e; ++i) {
        const Eigen::Vector3d x = position(keyed[i].point);
        const Eigen::Vector3d d = x - centre;
        s.sum_m += d;
        s.sum_xx_m2[0] += d.x() * d.x();
        s.sum_xx_m2[1] += d.x() * d.y();
        s.sum_xx_m2[2] += d.x() * d.z();
        s.sum_xx_m2[3] += d.y() * d.y();
        s.sum_xx_m2[4] += d.y() * d.z();
        s.sum_xx_m2[5] += d.z() * d.z();
        s.view_sum += (o - x).normalized();
      }
      out.coord[v] = k;
      out.count[v] = int32_t(e - b);
      out.sums[v] = s;
    }
  });
  return out;
}

std::shared_ptr<const GapFillPoints> GapFill(const LidarSource& src, double h) {
  if (src.gap_fill) return src.gap_fill;
  if (!src.HasGrid()) return std::make_shared<const GapFillPoints>();
  const Eigen::Matrix3d R = src.pose.q_world_sensor.toRotationMatrix();
  std::vector<KeyedPoint> keyed;
  bool in_range = true;
  const size_t end = KeyReturns(src, h, R, src.pose.o_world, &keyed, &in_range);
  return std::make_shared<const GapFillPoints>(FillGaps(src, h, R, src.pose.o_world, keyed, end));
}

records::VosselGeometry EmptyGeometry(double h) {
  records::VosselGeometry g;
  g.vossel_size_m = h;
  records::CanonicalizeVosselOrder(g);  // an empty index grid with the lattice's transform
  return g;
}

MergeResult MergeBinned(const records::VosselGeometry& base, const BinnedLidar& add,
                        records::VosselGeometry* out) {
  records::VosselInsertion ins = records::InsertVossels(base, add.coord, out);
  MergeResult result;
  result.new_vossels = out->size() - base.size();
  result.old_to_new = std::move(ins.old_to_new);
  result.touched.assign(out->size(), 0);
  for (size_t i = 0; i < add.size(); ++i) {
    const size_t k = size_t(ins.added_to_new[i]);
    if (ins.created[i]) {
      out->frame[k] = records::FrameOf(add.coord[i], add.count[i], add.sums[i], out->vossel_size_m);
    }
    out->point_count[k] += add.count[i];
    out->sums[k].Add(add.sums[i]);
    result.touched[k] = 1;
  }
  return result;
}

MergeResult MergeBinned(records::VosselGeometry& g, const BinnedLidar& add) {
  records::VosselGeometry merged;
  MergeResult result = MergeBinned(g, add, &merged);
  g = std::move(merged);
  return result;
}

absl::StatusOr<records::VosselGeometry> BuildGeometry(const std::vector<LidarSource>& lidars,
                                                      double h) {
  records::VosselGeometry g = EmptyGeometry(h);
  for (const LidarSource& lidar : lidars) {
    absl::StatusOr<BinnedLidar> binned = BinLidar(lidar, h);
    if (!binned.ok()) return binned.status();
    MergeBinned(g, *binned);
  }
  records::DeriveCentroidAndCovariance(g);
  ComputeNormals(g);
  return g;
}

namespace {

// PCA normal over the 3×3×3 neighbourhood of vossel v (the pooled scatter of the neighbours'
// points: Σ_j c_j (Σ_j + (μ_j − μ)(μ_j − μ)ᵀ)), oriented toward `view`; `view` itself when the
// neighbourhood holds no plane. `count(j)`, `centroid(j)`, `covariance(j)` describe vossel j.
template <typename Count, typename Centroid, typename Covariance>
Eigen::Vector3f PcaNormal(const openvdb::Int32Grid::ConstAccessor& acc, const openvdb::Coord& c,
                          const Eigen::Vector3f& view, Count count, Centroid centroid,
                          Covariance covariance) {
  double total = 0.0;
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  int neighbours = 0;
  int32_t ids[27];
  for (int dx = -1; dx <= 1; ++dx)
    for (int dy = -1; dy <= 1; ++dy)
      for (int dz = -1; dz <= 1; ++dz) {
        int32_t id;
        if (acc.probeValue(c.offsetBy(dx, dy, dz), id)) {
          ids[neighbours++] = id;
          total += count(id);
          mean += double(count(id)) * centroid(id).template cast<double>();
        }
      }
  mean /= total;
  Eigen::Matrix3d scatter = Eigen::Matrix3d::Zero();
  for (int j = 0; j < neighbours; ++j) {
    const auto& s = covariance(ids[j]);
    Eigen::Matrix3d cov;
    cov << s[0], s[1], s[2], s[1], s[3], s[4], s[2], s[4], s[5];
    const Eigen::Vector3d d = centroid(ids[j]).template cast<double>() - mean;
    scatter += double(count(ids[j])) * (cov + d * d.transpose());
  }
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
  return n;
}

}  // namespace

void ComputeNormals(records::VosselGeometry& g, const std::vector<uint8_t>* only) {
  const size_t nv = g.size();
  g.normal.resize(nv, Eigen::Vector3f::Zero());
  if (nv == 0) return;
  const bool frames = g.frame.size() == nv;
  const openvdb::Int32Grid& index = *g.index_grid;
  tbb::parallel_for(tbb::blocked_range<size_t>(0, nv, 2048), [&](const tbb::blocked_range<size_t>& r) {
    auto acc = index.getConstAccessor();
    for (size_t v = r.begin(); v != r.end(); ++v) {
      if (only != nullptr && !(*only)[v]) continue;
      const Eigen::Vector3f view =
          g.sums.empty() ? Eigen::Vector3f::Zero() : Eigen::Vector3f(g.sums[v].view_sum.cast<float>());
      g.normal[v] = PcaNormal(
          acc, g.coord[v], view, [&](int32_t j) { return g.point_count[j]; },
          [&](int32_t j) -> const Eigen::Vector3f& { return g.centroid_m[j]; },
          [&](int32_t j) -> const std::array<float, 6>& { return g.covariance_m2[j]; });
      if (!frames) continue;
      g.frame[v].normal = PcaNormal(
          acc, g.coord[v], g.frame[v].view, [&](int32_t j) { return g.frame[j].count; },
          [&](int32_t j) -> const Eigen::Vector3f& { return g.frame[j].centroid_m; },
          [&](int32_t j) -> const std::array<float, 6>& { return g.frame[j].covariance_m2; });
    }
  });
}

}  // namespace vasl::ingest

#include "lattice/tiles/tiling.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>

#include <tbb/parallel_for.h>

#include "absl/strings/str_cat.h"

namespace vasl::tiles {

std::string ToString(const TileKey& key) { return absl::StrCat(key.x, "_", key.y, "_", key.z); }

Box BoxOf(const TileKey& key, int T, double h) {
  Box b;
  b.min_m = h * (Eigen::Vector3d(key.x, key.y, key.z) * T - Eigen::Vector3d::Constant(0.5));
  b.max_m = b.min_m + Eigen::Vector3d::Constant(T * h);
  return b;
}

ViewCap CapOf(const Box& box, const Eigen::Vector3d& o, double grow_m) {
  ViewCap cap;
  const Eigen::Vector3d centre = 0.5 * (box.min_m + box.max_m);
  const double radius = 0.5 * (box.max_m - box.min_m).norm() + grow_m;
  const Eigen::Vector3d to_centre = centre - o;
  const double dist = to_centre.norm();
  const Eigen::Vector3d nearest = o.cwiseMax(box.min_m).cwiseMin(box.max_m);
  cap.near_m = (nearest - o).norm();
  double far2 = 0.0;
  for (int c = 0; c < 8; ++c) {
    const Eigen::Vector3d corner((c & 1) ? box.max_m.x() : box.min_m.x(),
                                 (c & 2) ? box.max_m.y() : box.min_m.y(),
                                 (c & 4) ? box.max_m.z() : box.min_m.z());
    far2 = std::max(far2, (corner - o).squaredNorm());
  }
  cap.far_m = std::sqrt(far2);
  if (dist <= radius) {
    cap.everywhere = true;
    cap.half_angle_rad = M_PI;
    return cap;
  }
  cap.dir = to_centre / dist;
  cap.half_angle_rad = std::asin(radius / dist);
  return cap;
}

bool CapsOverlap(const ViewCap& a, const ViewCap& b, double margin_rad) {
  if (a.everywhere || b.everywhere) return true;
  const double angle = std::acos(std::clamp(a.dir.dot(b.dir), -1.0, 1.0));
  return angle <= a.half_angle_rad + b.half_angle_rad + margin_rad;
}

namespace {

// Per block of kReachBlockPx² pixels, `op` (min or max) over its pixels of rows
// [row_begin, row_end), from `init`: parallel over rows of blocks; each pixel row is folded
// column by column into the block row's columns (contiguous, vectorised), then per block.
// With `cells` (a flag per block, as many as the raster's) only the flagged blocks are folded,
// each over its own pixels, and the others hold `elsewhere`.
template <typename Op>
ReachRaster PerCell(const std::vector<float>& depth_m, const geometry::EquirectSize& size,
                    int row_begin, int row_end, float init, Op op,
                    const std::vector<uint8_t>* cells = nullptr, float elsewhere = 0.0f) {
  const int W = size.width_px, H = size.height_px;
  ReachRaster r;
  r.size = {(W + kReachBlockPx - 1) / kReachBlockPx, (H + kReachBlockPx - 1) / kReachBlockPx};
  const size_t cell_count = size_t(r.size.width_px) * r.size.height_px;
  if (cells != nullptr && cells->size() != cell_count) cells = nullptr;
  r.max_depth_m.assign(cell_count, cells != nullptr ? elsewhere : init);
  row_begin = std::clamp(row_begin, 0, H);
  row_end = row_end < 0 ? H : std::clamp(row_end, row_begin, H);
  if (row_begin >= row_end || W <= 0) return r;
  const int first = row_begin / kReachBlockPx, last = (row_end - 1) / kReachBlockPx;
  tbb::parallel_for(first, last + 1, [&](int cj) {
    const int j0 = std::max(row_begin, cj * kReachBlockPx);
    const int j1 = std::min(row_end, (cj + 1) * kReachBlockPx);
    if (cells != nullptr) {
      for (int ci = 0; ci < r.size.width_px; ++ci) {
        const size_t c = size_t(cj) * r.size.width_px + ci;
        if ((*cells)[c] == 0) continue;
        const int i0 = ci * kReachBlockPx, i1 = std::min(W, i0 + kReachBlockPx);
        float cell = init;
        for (int j = j0; j < j1; ++j) {
          const float* in = &depth_m[size_t(j) * W];
          for (int i = i0; i < i1; ++i) cell = op(cell, in[i]);
        }
        r.max_depth_m[c] = cell;
      }
      return;
    }
    std::vector<float> columns(size_t(W), init);
    for (int j = j0; j < j1; ++j) {
      const float* in = &depth_m[size_t(j) * W];
      for (int i = 0; i < W; ++i) columns[i] = op(columns[i], in[i]);
    }
    float* cells = &r.max_depth_m[size_t(cj) * r.size.width_px];
    for (int i = 0; i < W; ++i) {
      float& cell = cells[i / kReachBlockPx];
      cell = op(cell, columns[i]);
    }
  });
  return r;
}

}  // namespace

ReachRaster ReachFromDepth(const std::vector<float>& depth_m, const geometry::EquirectSize& size,
                           const std::vector<uint8_t>* cells, float elsewhere) {
  return PerCell(depth_m, size, 0, size.height_px, -std::numeric_limits<float>::infinity(),
                 [](float a, float b) { return std::max(a, b); }, cells, elsewhere);
}

std::vector<float> CellMinFromDepth(const std::vector<float>& depth_m,
                                    const geometry::EquirectSize& size, int row_begin,
                                    int row_end) {
  return PerCell(depth_m, size, row_begin, row_end, std::numeric_limits<float>::infinity(),
                 [](float a, float b) { return std::min(a, b); })
      .max_depth_m;
}

bool Reaches(const ReachRaster& reach, const geometry::Pose& T_world_sensor, const ViewCap& cap,
             double min_depth_m) {
  const int W = reach.size.width_px, H = reach.size.height_px;
  if (W <= 0 || H <= 0) return true;  // no raster: assume it reaches
  const double dphi = 2.0 * M_PI / W, dpsi = M_PI / H;
  if (cap.everywhere) {
    for (float d : reach.max_depth_m) {
      if (d >= min_depth_m) return true;
    }
    return false;
  }
  const Eigen::Vector3d dir_s = T_world_sensor.q_world_sensor.conjugate() * cap.dir;
  const double psi_c = std::asin(std::clamp(dir_s.z(), -1.0, 1.0));
  // Half-diagonal of a cell on the sphere (bounded by its angular extents) plus the cap.
  const double reach_rad = cap.half_angle_rad + 0.5 * std::hypot(dphi, dpsi);
  const double cos_reach = std::cos(std::min(reach_rad, M_PI));
  const int j0 = std::max(0, int(std::floor((0.5 - (psi_c + reach_rad) / M_PI) * H)) - 1);
  const int j1 = std::min(H - 1, int(std::floor((0.5 - (psi_c - reach_rad) / M_PI) * H)) + 1);
  for (int j = j0; j <= j1; ++j) {
    const double psi = geometry::EquirectElevationRad(j + 0.5, reach.size);
    const double cpsi = std::cos(psi), spsi = std::sin(psi);
    const float* row = &reach.max_depth_m[size_t(j) * W];
    for (int i = 0; i < W; ++i) {
      if (row[i] < min_depth_m) continue;
      const double phi = geometry::EquirectAzimuthRad(i + 0.5, reach.size);
      const Eigen::Vector3d d(cpsi * std::cos(phi), cpsi * std::sin(phi), spsi);
      if (d.dot(dir_s) >= cos_reach) return true;
    }
  }
  return false;
}

bool CapCells::Reaches(const ViewCap& cap, const std::vector<float>& max_depth_m,
                       double min_depth_m) const {
  bool reached = false;
  ForEach(cap, [&](size_t cell, bool) {
    reached = double(max_depth_m[cell]) >= min_depth_m;
    return !reached;
  });
  return reached;
}

PixelSpan CapPixelSpan(const Eigen::Vector3d& d, double radius_rad,
                       const geometry::EquirectSize& size) {
  const int W = size.width_px, H = size.height_px;
  PixelSpan out;
  if (W <= 0 || H <= 0) return out;
  const double psi_c = std::asin(std::clamp(d.z(), -1.0, 1.0));
  const double r = std::min(radius_rad, M_PI);
  out.row_first = std::max(0, int(std::floor((0.5 - (psi_c + r) / M_PI) * H)) - 1);
  out.row_last = std::min(H - 1, int(std::floor((0.5 - (psi_c - r) / M_PI) * H)) + 1);
  out.col_count = W;
  if (std::abs(psi_c) + r < 0.5 * M_PI - 1e-9) {
    // Pixel i's centre lies at u = i + ½: those within `half` of the centre's u, and one more.
    const double half = std::asin(std::min(1.0, std::sin(r) / std::cos(psi_c))) /
                        (2.0 * M_PI) * W;
    if (2.0 * half + 4.0 < double(W)) {
      const double centre = (0.5 - std::atan2(d.y(), d.x()) / (2.0 * M_PI)) * W;
      const int first = int(std::floor(centre - half)) - 1;
      out.col_count = int(std::floor(centre + half)) + 1 - first + 1;
      out.col_first = ((first % W) + W) % W;
    }
  }
  return out;
}

CapCells::CapCells(const geometry::EquirectSize& size, const geometry::Pose& T_world_sensor)
    : size_(size),
      R_sensor_world_(T_world_sensor.q_world_sensor.conjugate().toRotationMatrix()) {
  const int W = size.width_px, H = size.height_px;
  if (W <= 0 || H <= 0) return;
  half_diag_ = 0.5 * std::hypot(2.0 * M_PI / W, M_PI / H);
  dir_.resize(size_t(W) * size_t(H));
  for (int j = 0; j < H; ++j) {
    const double psi = geometry::EquirectElevationRad(j + 0.5, size);
    for (int i = 0; i < W; ++i) {
      const double phi = geometry::EquirectAzimuthRad(i + 0.5, size);
      dir_[size_t(j) * W + i] = Eigen::Vector3d(std::cos(psi) * std::cos(phi),
                                                std::cos(psi) * std::sin(phi), std::sin(psi));
    }
  }
}

std::vector<uint8_t> CellCoverage(const geometry::EquirectSize& size,
                                  const geometry::Pose& T_world_sensor,
                                  const std::vector<ViewCap>& caps) {
  const CapCells cells(size, T_world_sensor);
  std::vector<uint8_t> out(cells.cell_count(), 0);
  for (const ViewCap& cap : caps) {
    cells.ForEach(cap, [&out](size_t c, bool whole) {
      out[c] = whole ? uint8_t{2} : std::max(out[c], uint8_t{1});
      return true;
    });
  }
  return out;
}

ReachRaster MergeReach(const ReachRaster& old, const ReachRaster& fresh,
                       const std::vector<uint8_t>& coverage) {
  ReachRaster out = old;
  for (size_t c = 0; c < out.max_depth_m.size(); ++c) {
    const float a = old.max_depth_m[c], b = fresh.max_depth_m[c];
    out.max_depth_m[c] = coverage[c] == 2 ? b : coverage[c] == 1 ? std::max(a, b) : std::min(a, b);
  }
  return out;
}

std::string SerializeReach(const ReachRaster& reach) {
  std::string out = "VRCH";
  const int32_t dims[2] = {reach.size.width_px, reach.size.height_px};
  out.append(reinterpret_cast<const char*>(dims), sizeof(dims));
  out.append(reinterpret_cast<const char*>(reach.max_depth_m.data()),
             reach.max_depth_m.size() * sizeof(float));
  return out;
}

absl::StatusOr<ReachRaster> ParseReach(const std::string& bytes) {
  if (bytes.size() < 12 || bytes.compare(0, 4, "VRCH") != 0) {
    return absl::DataLossError("not a reach raster (no VRCH header)");
  }
  int32_t dims[2];
  std::memcpy(dims, bytes.data() + 4, sizeof(dims));
  ReachRaster r;
  r.size = {dims[0], dims[1]};
  const size_t n = size_t(std::max(0, dims[0])) * size_t(std::max(0, dims[1]));
  if (dims[0] <= 0 || dims[1] <= 0 || bytes.size() != 12 + n * sizeof(float)) {
    return absl::DataLossError(absl::StrCat("reach raster of ", dims[0], "x", dims[1], " has ",
                                            bytes.size(), " bytes"));
  }
  r.max_depth_m.resize(n);
  std::memcpy(r.max_depth_m.data(), bytes.data() + 12, n * sizeof(float));
  return r;
}

}  // namespace vasl::tiles

#include "lattice/ingest/visibility.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <optional>

#include <tbb/blocked_range.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>

#include "lattice/memory/buffer_pool.h"
#include "lattice/memory/isa.h"
#include "lattice/memory/lanes.h"
#include "lattice/tiles/tiling.h"

namespace vasl::ingest {

geometry::EquirectSize DepthPanoramaSize(double pitch_rad, int max_width_px) {
  // Whole reach cells (tiles::kReachBlockPx pixels) along both axes: a reach cell's pixels
  // then span exactly the angles tiles::Reaches and tiles::CellCoverage give the cell.
  constexpr int kCell = tiles::kReachBlockPx;
  const int most_cells = std::max(2, max_width_px / (2 * kCell));
  const double rows =
      std::clamp(M_PI / std::max(pitch_rad, 1e-6), 32.0, double(most_cells * kCell));
  const int height = std::clamp(int(std::lround(rows / kCell)), 2, most_cells) * kCell;
  return {2 * height, height};
}

namespace {

/// The pixel-centre directions of a row j (RenderDepthPanorama): q = cosφ·a + sinφ·b + c in the
/// world frame, with a = cosψ_j·R x̂, b = cosψ_j·R ŷ, c = sinψ_j·R ẑ (R world-from-sensor).
struct RowBasis {
  double a[3], b[3], c[3];
};

/// One vossel's splat (RenderDepthPanorama), set up once for every row it covers.
struct VosselSplat {
  double d[3];         ///< unit direction to the vossel's centre (world frame)
  double cos_a;        ///< the cap: q·d ≥ cos a
  double n[3];         ///< its surfel's normal (zero: none)
  double plane_d;      ///< its plane n·x = plane_d (sensor at the origin)
  double centre[3];    ///< the cell's centre, relative to the sensor
  double half_cell_m;  ///< the cell's half edge dilated by σ
  double range_m;      ///< the centre's range
  double rho;          ///< |d_xy| in the sensor frame (cos ψ of d)
  double d_z;          ///< d_z in the sensor frame (sin ψ of d)
  double u;            ///< d's column coordinate (EquirectProject)
  int j0, j1;          ///< the rows whose centres can lie in the cap
  bool has_plane;      ///< a surfel (else the centre's range everywhere in the cap)
};

/// Keeps, at each of a row's run of n contiguous columns, the min of its depth and a vossel's
/// splat there: the range at which the pixel's direction q (cos_phi, sin_phi of the columns,
/// the row's basis) crosses the splat's plane, where q lies in its cap and the crossing lies
/// within its dilated cell; the centre's range everywhere in the cap for a splat without a
/// plane. Branch-free over contiguous memory, so that it vectorises (SplatRowOn: AVX2 where
/// the CPU has it, rounding as the baseline does, memory/isa.h; GCC vectorises the selects
/// only when told that floating-point operations do not trap, which they do not here: no FP
/// exception is unmasked); a min is order-free, so the panorama does not depend on the order
/// splats come in.
[[gnu::always_inline, gnu::optimize("no-trapping-math")]] inline void SplatRow(
    const RowBasis& r, const VosselSplat& s, const double* cos_phi, const double* sin_phi, int n,
    float* depth) {
  const double a0 = r.a[0], a1 = r.a[1], a2 = r.a[2], b0 = r.b[0], b1 = r.b[1], b2 = r.b[2];
  const double c0 = r.c[0], c1 = r.c[1], c2 = r.c[2], d0 = s.d[0], d1 = s.d[1], d2 = s.d[2];
  const double cos_a = s.cos_a;
  constexpr double kNone = std::numeric_limits<double>::infinity();
  if (!s.has_plane) {
    const double range = double(float(s.range_m));
    for (int x = 0; x < n; ++x) {
      const double cp = cos_phi[x], sp = sin_phi[x];
      const double q0 = cp * a0 + sp * b0 + c0;
      const double q1 = cp * a1 + sp * b1 + c1;
      const double q2 = cp * a2 + sp * b2 + c2;
      const float v = float(q0 * d0 + q1 * d1 + q2 * d2 < cos_a ? kNone : range);
      depth[x] = v < depth[x] ? v : depth[x];
    }
    return;
  }
  const double n0 = s.n[0], n1 = s.n[1], n2 = s.n[2], plane_d = s.plane_d;
  const double e0 = s.centre[0], e1 = s.centre[1], e2 = s.centre[2], half = s.half_cell_m;
  for (int x = 0; x < n; ++x) {
    const double cp = cos_phi[x], sp = sin_phi[x];
    const double q0 = cp * a0 + sp * b0 + c0;
    const double q1 = cp * a1 + sp * b1 + c1;
    const double q2 = cp * a2 + sp * b2 + c2;
    const double nq = n0 * q0 + n1 * q1 + n2 * q2;
    const double t = plane_d / nq;
    const double x0 = __builtin_fabs(t * q0 - e0), x1 = __builtin_fabs(t * q1 - e1);
    const double x2 = __builtin_fabs(t * q2 - e2);
    const double x01 = x0 < x1 ? x1 : x0;  // std::max, as Eigen's maxCoeff takes it
    const double far = x01 < x2 ? x2 : x01;
    const bool miss = (q0 * d0 + q1 * d1 + q2 * d2 < cos_a) | (__builtin_fabs(nq) < 1e-9) |
                      !(t > 0.0) | (far > half);
    const float v = float(miss ? kNone : t);
    depth[x] = v < depth[x] ? v : depth[x];
  }
}

using SplatRowFn = void (*)(const RowBasis&, const VosselSplat&, const double*, const double*,
                            int, float*);
[[gnu::optimize("no-trapping-math")]] void SplatRowBaseline(
    const RowBasis& r, const VosselSplat& s, const double* cos_phi, const double* sin_phi, int n,
    float* depth) {
  SplatRow(r, s, cos_phi, sin_phi, n, depth);
}
#if VASL_ISA_VARIANTS
[[gnu::target("avx2"), gnu::optimize("no-trapping-math")]] void SplatRowAvx2(
    const RowBasis& r, const VosselSplat& s, const double* cos_phi, const double* sin_phi, int n,
    float* depth) {
  SplatRow(r, s, cos_phi, sin_phi, n, depth);
}
#endif
/// SplatRow compiled for the widest instruction set the CPU runs (memory::WidestIsa): AVX2 or
/// the baseline (an AVX-512 variant was slower: BM_DepthPanorama/camera_station_12 36 → 41 ms).
SplatRowFn SplatRowOn(memory::Isa isa) {
#if VASL_ISA_VARIANTS
  if (isa >= memory::Isa::kAvx2) return SplatRowAvx2;
#endif
  (void)isa;
  return SplatRowBaseline;
}

/// acos(x), x in [−1, 1], to within kAcosBoundErrRad (Abramowitz & Stegun 4.4.45: at most
/// 6.8e-5 rad, measured over 2·10⁶ points of [−1, 1]): a bound of a splat's chord in a row,
/// never a depth.
constexpr double kAcosBoundErrRad = 1e-4;
inline double AcosBound(double x) {
  const double ax = x < 0.0 ? -x : x;
  const double r =
      std::sqrt(1.0 - ax) * (1.5707288 + ax * (-0.2121144 + ax * (0.0742610 + ax * -0.0187293)));
  return x < 0.0 ? M_PI - r : r;
}

/// Rows of a band: each band of the panorama is splatted by one task into its own rows, which
/// stay in the core's cache (2048 columns: 128 KB), without atomics.
constexpr int kBandRows = 16;

/// Front-to-back culling of RenderDepthPanorama: blocks of consecutive vossels, tested against
/// the farthest depth per reach cell of the passes before; the shares of the blocks (nearest
/// first) splatted by the end of each pass; not below kCullMinVossels splatted vossels.
constexpr size_t kCullBlock = 64;
constexpr double kCullPassShares[] = {0.125, 0.25, 0.5, 1.0};

}  // namespace

DepthPanorama RenderDepthPanorama(const records::VosselGeometry& g, const geometry::Pose& pose,
                                  const geometry::EquirectSize& size, double divergence_rad,
                                  const std::vector<uint8_t>* splat_only,
                                  const std::vector<uint8_t>* cells) {
  constexpr int kCell = tiles::kReachBlockPx;
  const int cells_w = size.width_px / kCell;
  if (cells != nullptr && (size.width_px % kCell != 0 || size.height_px % kCell != 0 ||
                           cells->size() != size_t(cells_w) * (size.height_px / kCell))) {
    cells = nullptr;  // not whole cells of this panorama: splat every pixel (exact, slower)
  }
  const SplatRowFn splat_row = SplatRowOn(memory::WidestIsa());
  DepthPanorama out;
  out.pose = pose;
  out.size = size;
  const int W = size.width_px, H = size.height_px;
  const size_t npix = size_t(W) * H;
  std::vector<float>& depth = out.depth_m;
  depth = memory::TakeFloats(npix, std::numeric_limits<float>::infinity());
  out.splat_row_begin = H;  // no row splatted yet
  out.splat_row_end = 0;
  // With `cells`: a summed-area table of the flagged cells, so that a splat whose pixels lie
  // in unflagged cells only is passed over before any per-row work.
  const int cells_h = cells != nullptr ? size.height_px / kCell : 0;
  std::vector<int32_t> flagged_sum;
  if (cells != nullptr) {
    flagged_sum.assign(size_t(cells_w + 1) * size_t(cells_h + 1), 0);
    for (int cj = 0; cj < cells_h; ++cj) {
      for (int ci = 0; ci < cells_w; ++ci) {
        flagged_sum[size_t(cj + 1) * (cells_w + 1) + ci + 1] =
            ((*cells)[size_t(cj) * cells_w + ci] != 0 ? 1 : 0) +
            flagged_sum[size_t(cj) * (cells_w + 1) + ci + 1] +
            flagged_sum[size_t(cj + 1) * (cells_w + 1) + ci] -
            flagged_sum[size_t(cj) * (cells_w + 1) + ci];
      }
    }
  }
  // Flagged cells among cell rows [r0, r1] and cell columns [c0, c1] (0 ≤ c0 ≤ c1 < cells_w).
  auto flagged_in = [&](int r0, int r1, int c0, int c1) {
    const size_t s = size_t(cells_w + 1);
    return flagged_sum[size_t(r1 + 1) * s + c1 + 1] - flagged_sum[size_t(r0) * s + c1 + 1] -
           flagged_sum[size_t(r1 + 1) * s + c0] + flagged_sum[size_t(r0) * s + c0];
  };

  // Pixel-centre directions, separable: q = (cosψ cosφ, cosψ sinφ, sinψ) in the sensor frame,
  // and in the world frame q_w = cosφ·A_j + sinφ·B_j + C_j (RowBasis): a pixel's tests then
  // take a few products, with every vossel quantity in the world frame (rotations keep the
  // dot products).
  std::vector<double> cos_phi(W), sin_phi(W), cos_psi(H), sin_psi(H);
  for (int i = 0; i < W; ++i) {
    const double phi = geometry::EquirectAzimuthRad(i + 0.5, size);
    cos_phi[i] = std::cos(phi);
    sin_phi[i] = std::sin(phi);
  }
  for (int j = 0; j < H; ++j) {
    const double psi = geometry::EquirectElevationRad(j + 0.5, size);
    cos_psi[j] = std::cos(psi);
    sin_psi[j] = std::sin(psi);
  }
  const Eigen::Matrix3d R_world_sensor = pose.q_world_sensor.toRotationMatrix();
  const Eigen::Matrix3d R_sensor_world = R_world_sensor.transpose();
  std::vector<RowBasis> basis(H);
  for (int j = 0; j < H; ++j) {
    for (int e = 0; e < 3; ++e) {
      basis[j].a[e] = cos_psi[j] * R_world_sensor(e, 0);
      basis[j].b[e] = cos_psi[j] * R_world_sensor(e, 1);
      basis[j].c[e] = sin_psi[j] * R_world_sensor(e, 2);
    }
  }
  const double h = g.vossel_size_m;
  const double sphere_m = 0.5 * std::sqrt(3.0) * h;  // bounding sphere of a vossel (§5)
  const double dpsi = geometry::ElevationPitchRad(size);
  const double px_per_rad = W / (2.0 * M_PI);

  // A vossel's splat set up once (appended to `mine`), unless it cannot fall in a flagged cell
  // or holds the sensor.
  auto set_up = [&](size_t k, std::vector<VosselSplat>& mine) {
    const Eigen::Vector3d c_w =
        h * Eigen::Vector3d(g.coord[k].x(), g.coord[k].y(), g.coord[k].z()) - pose.o_world;
    const double range = c_w.norm();
    if (range <= sphere_m) return;  // the sensor sits inside this vossel
    const Eigen::Vector3d d_w = c_w / range;
    const Eigen::Vector3d d = R_sensor_world * d_w;
    // The splat: the vossel's bounding sphere dilated by the footprint σ(r) = r·tan(θ/2) (§3).
    const double sigma_m = geometry::SpotSigmaM(range, divergence_rad);
    const double a = std::asin(std::min(1.0, (sphere_m + sigma_m) / range));
    const Eigen::Vector2d uv = geometry::EquirectProject(d, size);
    // The rows whose centres can lie within a of d (floor and ceil keep them conservative).
    const double rows = a / dpsi;
    const int j0 = std::max(0, int(std::floor(uv.y() - 0.5 - rows)));
    const int j1 = std::min(H - 1, int(std::ceil(uv.y() - 0.5 + rows)));
    if (j0 > j1) return;
    const double rho = std::hypot(d.x(), d.y());
    if (cells != nullptr) {
      // The cap's columns: clear of the poles it spans the azimuths within asin(sin a / ρ)
      // of d's (ρ = cos ψ_d); one pixel of slack either side.
      int c0 = 0, c1 = cells_w - 1;
      const double sin_a = std::sin(a);
      if (sin_a < rho && std::asin(std::min(1.0, d.z() < 0 ? -d.z() : d.z())) + a <
                             0.5 * M_PI - 1e-9) {
        const double half_px = std::asin(sin_a / rho) * px_per_rad + 1.0;
        if (2.0 * half_px + 2.0 < double(W)) {
          c0 = int(std::floor((uv.x() - 0.5 - half_px) / kCell));
          c1 = int(std::floor((uv.x() - 0.5 + half_px) / kCell));
        }
      }
      const int r0 = j0 / kCell, r1 = j1 / kCell;
      int hits;
      if (c1 - c0 + 1 >= cells_w) {
        hits = flagged_in(r0, r1, 0, cells_w - 1);
      } else {
        const int w0 = ((c0 % cells_w) + cells_w) % cells_w;
        const int w1 = ((c1 % cells_w) + cells_w) % cells_w;
        hits = w0 <= w1 ? flagged_in(r0, r1, w0, w1)
                        : flagged_in(r0, r1, w0, cells_w - 1) + flagged_in(r0, r1, 0, w1);
      }
      if (hits == 0) return;
    }
    const Eigen::Vector3d x_w = g.FrameCentroid(k).cast<double>() - pose.o_world;
    const Eigen::Vector3d n_w = g.FrameNormal(k).cast<double>();
    // Surfel splat: the range where a pixel's ray crosses the vossel's plane, kept only where
    // that crossing lies inside the vossel's cell dilated by σ; a ray that grazes the plane
    // outside the vossel does not see it, and silhouettes are not inflated.
    VosselSplat s;
    s.has_plane = n_w.squaredNorm() > 0.5;
    s.plane_d = n_w.dot(x_w);
    s.cos_a = std::cos(a);
    s.half_cell_m = 0.5 * h + sigma_m;
    s.range_m = range;
    for (int e = 0; e < 3; ++e) {
      s.d[e] = d_w[e];
      s.n[e] = n_w[e];
      s.centre[e] = c_w[e];
    }
    s.rho = rho;
    s.d_z = d.z();
    s.u = uv.x();
    s.j0 = j0;
    s.j1 = j1;
    mine.push_back(s);
  };

  // The splats set up (per thread), binned by bands of rows (a splat spanning several bands
  // is in each) and splatted band by band.
  auto splat_bands = [&](tbb::enumerable_thread_specific<std::vector<VosselSplat>>& set_up) {
    const int bands = (H + kBandRows - 1) / kBandRows;
    std::vector<size_t> band_begin(size_t(bands) + 1, 0);
    for (const std::vector<VosselSplat>& list : set_up) {
      for (const VosselSplat& s : list) {
        for (int b = s.j0 / kBandRows; b <= s.j1 / kBandRows; ++b) ++band_begin[size_t(b) + 1];
        out.splat_row_begin = std::min(out.splat_row_begin, s.j0);
        out.splat_row_end = std::max(out.splat_row_end, s.j1 + 1);
      }
    }
    for (int b = 0; b < bands; ++b) band_begin[size_t(b) + 1] += band_begin[size_t(b)];
    std::vector<const VosselSplat*> in_band(band_begin.back());
    {
      std::vector<size_t> fill(band_begin.begin(), band_begin.end() - 1);
      for (const std::vector<VosselSplat>& list : set_up) {
        for (const VosselSplat& s : list) {
          for (int b = s.j0 / kBandRows; b <= s.j1 / kBandRows; ++b) {
            in_band[fill[size_t(b)]++] = &s;
          }
        }
      }
    }

    // Each band splatted by one task: in each row of a splat, the columns of the cap's chord:
    // with ρ = |d_xy|, a pixel of row j is within a when cos(φ − φ_d) ≥ (cos a − sinψ_j d_z) /
    // (cosψ_j ρ); the chord's half width bounded from above (AcosBound) and one pixel of slack
    // either side, SplatRow's cap test decides.
    tbb::parallel_for(0, bands, [&](int b) {
      const int band_j0 = b * kBandRows, band_j1 = std::min(H, band_j0 + kBandRows) - 1;
      for (size_t n = band_begin[size_t(b)]; n != band_begin[size_t(b) + 1]; ++n) {
        const VosselSplat& s = *in_band[n];
        for (int j = std::max(s.j0, band_j0); j <= std::min(s.j1, band_j1); ++j) {
          int i0 = 0, i1 = W - 1;
          const double across = cos_psi[j] * s.rho;
          if (across > 1e-9) {
            const double c = (s.cos_a - sin_psi[j] * s.d_z) / across;
            if (c > 1.0 + 1e-9) continue;  // the cap misses this row's centres
            if (c > -1.0) {
              const double half_px =
                  (AcosBound(std::min(c, 1.0)) + kAcosBoundErrRad) * px_per_rad + 1.0;
              if (2.0 * half_px + 2.0 < double(W)) {
                i0 = int(std::floor(s.u - 0.5 - half_px));
                i1 = int(std::ceil(s.u - 0.5 + half_px));
              }
            }
          }
          float* depth_row = &depth[size_t(j) * W];
          // The columns i0..i1 wrap at most once (the chord is narrower than the panorama): one
          // or two runs of contiguous columns.
          const int first = geometry::WrapColumn(i0, W);
          const int count = std::min(i1 - i0 + 1, W);
          for (int begin = first, left = count; left > 0;) {
            const int n_px = std::min(left, W - begin);
            splat_row(basis[j], s, &cos_phi[begin], &sin_phi[begin], n_px, depth_row + begin);
            left -= n_px;
            begin = 0;
          }
        }
      }
    });
  };

  // Front to back: blocks of kCullBlock consecutive vossels (neighbours in the lattice's
  // order) in passes of growing distance; from the second pass on, a block whose splats all
  // lie behind the farthest depth already splatted in every reach cell they can fall in is left
  // out (exact: splats only lower a depth, so they would lie behind the final one too). Below
  // kCullMinVossels, or on a panorama of partial reach cells, one pass of every block.
  const size_t splatted =
      splat_only == nullptr ? g.size()
                            : size_t(std::count(splat_only->begin(), splat_only->end(), 1));
  const bool cull = splatted >= kCullMinVossels && W % kCell == 0 && H % kCell == 0;
  // With `cells`, every block's cap is tested against the flagged cells before its vossels are
  // set up one by one, and the culling passes read the flagged cells alone (their depth is all
  // a revisit keeps): -inf in the others, which no block then reaches.
  const bool by_cells = cells != nullptr;
  struct Block {
    size_t begin = 0, end = 0, vossels = 0;
    tiles::ViewCap cap;
    double behind_m = 0.0;  ///< every splat of the block lies at least this far
  };
  std::vector<Block> blocks((g.size() + kCullBlock - 1) / kCullBlock);
  tbb::parallel_for(size_t(0), blocks.size(), [&](size_t b) {
    Block& block = blocks[b];
    block.begin = b * kCullBlock;
    block.end = std::min(g.size(), block.begin + kCullBlock);
    tiles::Box box{Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity()),
                   Eigen::Vector3d::Constant(-std::numeric_limits<double>::infinity())};
    for (size_t k = block.begin; k != block.end; ++k) {
      if (splat_only != nullptr && !(*splat_only)[k]) continue;
      const openvdb::Coord& ijk = g.coord[k];
      const Eigen::Vector3d c = h * Eigen::Vector3d(ijk.x(), ijk.y(), ijk.z());
      box.min_m = box.min_m.cwiseMin(c);
      box.max_m = box.max_m.cwiseMax(c);
      ++block.vossels;
    }
    if (!(cull || by_cells) || block.vossels == 0) return;
    // Each splat lies in its centre's cap of the bounding sphere grown by σ at its range,
    // at depths of at least its centre's range less the dilated cell's half-diagonal.
    const double sigma_m =
        geometry::SpotSigmaM(tiles::CapOf(box, pose.o_world, 0.0).far_m, divergence_rad);
    block.cap = tiles::CapOf(box, pose.o_world, sphere_m + sigma_m);
    block.behind_m = block.cap.near_m - std::sqrt(3.0) * (0.5 * h + sigma_m) -
                     1e-6 * (1.0 + block.cap.far_m);
  });
  std::vector<size_t> order;
  for (size_t b = 0; b < blocks.size(); ++b) {
    if (blocks[b].vossels > 0) order.push_back(b);
  }
  std::vector<double> shares{1.0};  // without culling: one pass, in the lattice's order
  std::optional<tiles::CapCells> grid;
  if (cull) {
    std::sort(order.begin(), order.end(), [&](size_t x, size_t y) {
      return blocks[x].cap.near_m != blocks[y].cap.near_m
                 ? blocks[x].cap.near_m < blocks[y].cap.near_m
                 : x < y;
    });
    shares.assign(std::begin(kCullPassShares), std::end(kCullPassShares));
  }
  if (cull || by_cells) grid.emplace(geometry::EquirectSize{W / kCell, H / kCell}, pose);
  size_t done = 0;  // blocks of `order` passed
  for (double share : shares) {
    const size_t end = std::min(order.size(), size_t(std::ceil(share * double(order.size()))));
    if (end <= done) continue;
    std::vector<uint8_t> keep(end - done, 1);
    if (done > 0 || by_cells) {
      // With cells: the flagged cells' farthest depth (+inf before any splat), -inf in the
      // others, which no block reaches.
      const tiles::ReachRaster farthest = tiles::ReachFromDepth(
          depth, size, cells, -std::numeric_limits<float>::infinity());
      tbb::parallel_for(done, end, [&](size_t n) {
        const Block& block = blocks[order[n]];
        keep[n - done] = block.cap.everywhere ||
                         grid->Reaches(block.cap, farthest.max_depth_m, block.behind_m);
      });
    }
    tbb::enumerable_thread_specific<std::vector<VosselSplat>> pass;
    tbb::parallel_for(done, end, [&](size_t n) {
      if (!keep[n - done]) return;
      const Block& block = blocks[order[n]];
      std::vector<VosselSplat>& mine = pass.local();
      for (size_t k = block.begin; k != block.end; ++k) {
        if (splat_only == nullptr || (*splat_only)[k]) set_up(k, mine);
      }
    });
    splat_bands(pass);
    done = end;
  }

  // A revisit reads flagged cells only: the others stay +inf (rows no splat reached are).
  if (cells != nullptr && out.splat_row_begin < out.splat_row_end) {
    tbb::parallel_for(out.splat_row_begin, out.splat_row_end, [&](int j) {
      const uint8_t* cell_row = &(*cells)[size_t(j / kCell) * size_t(cells_w)];
      float* depth_row = &depth[size_t(j) * W];
      for (int ci = 0; ci < cells_w; ++ci) {
        if (cell_row[ci]) continue;
        std::fill(depth_row + ci * kCell, depth_row + (ci + 1) * kCell,
                  std::numeric_limits<float>::infinity());
      }
    });
  }
  return out;
}

void MaskOutsideCone(DepthPanorama& depth, const Eigen::Vector3d& axis, double half_angle_rad) {
  if (half_angle_rad >= M_PI) return;
  const int W = depth.size.width_px, H = depth.size.height_px;
  const double cos_max = std::cos(half_angle_rad);
  const Eigen::Vector3d a = axis.normalized();
  tbb::parallel_for(0, H, [&](int j) {
    for (int i = 0; i < W; ++i) {
      const Eigen::Vector3d d = geometry::EquirectUnproject(i + 0.5, j + 0.5, depth.size);
      if (d.dot(a) < cos_max) depth.depth_m[size_t(j) * W + i] = 0.0f;
    }
  });
}

void DilateDepthPanorama(DepthPanorama& depth, int radius_px, int row_begin, int row_end) {
  if (radius_px <= 0) return;
  const int W = depth.size.width_px, H = depth.size.height_px;
  row_begin = std::clamp(row_begin, 0, H);
  row_end = row_end < 0 ? H : std::clamp(row_end, row_begin, H);
  if (row_begin >= row_end) return;
  const int r = std::min(radius_px, W);
  // Separable min filter: rows (wrapping), then columns (clamped); the row pass covers the rows
  // the column pass reads, and only those are held. Both inner loops run over contiguous
  // columns, one window offset at a time.
  const int t0 = std::max(0, row_begin - r), t1 = std::min(H, row_end + r);
  std::vector<float> tmp(size_t(t1 - t0) * W);
  tbb::parallel_for(tbb::blocked_range<int>(t0, t1, 8), [&](const tbb::blocked_range<int>& rows) {
    std::vector<float> padded(size_t(W) + 2 * r);  // the row with r columns wrapped either side
    for (int j = rows.begin(); j != rows.end(); ++j) {
      const float* row = &depth.depth_m[size_t(j) * W];
      std::copy(row + W - r, row + W, padded.begin());
      std::copy(row, row + W, padded.begin() + r);
      std::copy(row, row + r, padded.begin() + r + W);
      float* out = &tmp[size_t(j - t0) * W];
      std::copy(padded.begin(), padded.begin() + W, out);
      for (int d = 1; d <= 2 * r; ++d) {
        const float* in = padded.data() + d;
        for (int i = 0; i < W; ++i) out[i] = std::min(out[i], in[i]);
      }
    }
  });
  tbb::parallel_for(tbb::blocked_range<int>(row_begin, row_end, 8),
                    [&](const tbb::blocked_range<int>& rows) {
    for (int j = rows.begin(); j != rows.end(); ++j) {
      float* out = &depth.depth_m[size_t(j) * W];
      const int a = std::max(t0, j - r), b = std::min(t1 - 1, j + r);
      std::copy_n(&tmp[size_t(a - t0) * W], W, out);
      for (int k = a + 1; k <= b; ++k) {
        const float* in = &tmp[size_t(k - t0) * W];
        for (int i = 0; i < W; ++i) out[i] = std::min(out[i], in[i]);
      }
    }
  });
}

namespace {

/// One vossel's patch for its visibility tests: its frame centroid x and tangents t1, t2, the
/// sensor o and R_sensor_world (row-major), as the scalar sample reads them.
struct PatchFrame {
  double x[3], t1[3], t2[3], o[3], R[9];
};

/// The lit samples among ComputeVisibility's 16 grid samples of a patch (offsets sa, sb along
/// t1, t2), L at a time (memory::Lanes): each lane takes the operations of the scalar sample
/// (the point, its sensor-frame direction, its range, and geometry::EquirectProject with
/// geometry::Atan2Lanes) in the same order, so that it reads the pixel the scalar sample reads
/// and compares the same range: the same count, bit for bit
/// (VisibilityShortcutTest.GridSamplesCountAsTheScalarSamples). −1 when a sample's direction
/// is not finite or lies on the sensor's axis (Atan2's special cases): the caller takes the
/// scalar samples.
template <int L>
[[gnu::always_inline]] inline int LitGridSamples(const double* sa, const double* sb,
                                                 const PatchFrame& f, const float* depth, int W,
                                                 int H, double tolerance_m) {
  using V = typename memory::Lanes<L>::Doubles;
  using I = typename memory::Lanes<L>::Int64s;
  int lit = 0;
  for (int s0 = 0; s0 < 16; s0 += L) {
    V a, b;
    std::memcpy(&a, sa + s0, sizeof a);
    std::memcpy(&b, sb + s0, sizeof b);
    V v[3], p[3];
    for (int c = 0; c < 3; ++c) v[c] = ((f.x[c] + a * f.t1[c]) + b * f.t2[c]) - f.o[c];
    for (int r = 0; r < 3; ++r) {
      p[r] = (f.R[3 * r] * v[0] + f.R[3 * r + 1] * v[1]) + f.R[3 * r + 2] * v[2];
    }
    const V xy = p[0] * p[0] + p[1] * p[1];
    const V rr = xy + p[2] * p[2];
    V hxy, range;
    for (int l = 0; l < L; ++l) {
      hxy[l] = std::sqrt(xy[l]);
      range[l] = std::sqrt(rr[l]);
    }
    const I finite = (rr == rr) & (rr < std::numeric_limits<double>::infinity());
    const I axis = (p[0] == 0.0) & (p[1] == 0.0);
    for (int l = 0; l < L; ++l) {
      if (!finite[l] || axis[l]) return -1;
    }
    V phi, psi;
    geometry::Atan2Lanes<V, I>(p[1], p[0], phi);
    geometry::Atan2Lanes<V, I>(p[2], hxy, psi);
    V u = double(W) * (0.5 - phi / (2.0 * M_PI));
    const V vv = double(H) * (0.5 - psi / M_PI);
    u = u >= double(W) ? u - double(W) : u;  // φ = −π maps to u = W, the seam: wrap to 0
    u = u < 0.0 ? u + double(W) : u;
    const V threshold = range - tolerance_m;
    for (int l = 0; l < L; ++l) {
      const int i = geometry::WrapColumn(int(std::floor(u[l])), W);
      const int j = std::clamp(int(std::floor(vv[l])), 0, H - 1);
      lit += depth[size_t(j) * W + i] >= threshold[l] ? 1 : 0;
    }
  }
  return lit;
}

using LitGridFn = int (*)(const double*, const double*, const PatchFrame&, const float*, int, int,
                          double);
int LitGridBaseline(const double* sa, const double* sb, const PatchFrame& f, const float* depth,
                    int W, int H, double tolerance_m) {
  return LitGridSamples<2>(sa, sb, f, depth, W, H, tolerance_m);
}
#if VASL_ISA_VARIANTS
[[gnu::target("avx2")]] int LitGridAvx2(const double* sa, const double* sb, const PatchFrame& f,
                                        const float* depth, int W, int H, double tolerance_m) {
  return LitGridSamples<4>(sa, sb, f, depth, W, H, tolerance_m);
}
[[gnu::target("arch=x86-64-v4")]] int LitGridX86_64_V4(const double* sa, const double* sb,
                                                      const PatchFrame& f, const float* depth,
                                                      int W, int H, double tolerance_m) {
  return LitGridSamples<8>(sa, sb, f, depth, W, H, tolerance_m);
}
#endif
/// LitGridSamples for the widest instruction set the CPU runs (memory::WidestIsa): on the
/// corridor's twelfth station, BM_Visibility 31-32 ms with the samples one by one, 21-23 ms in
/// lanes (AVX-512 21.2-22.4 ms, AVX2 22.2-22.9: the wider taken).
LitGridFn LitGridOn(memory::Isa isa) {
#if VASL_ISA_VARIANTS
  if (isa >= memory::Isa::kX86_64_V4) return LitGridX86_64_V4;
  if (isa >= memory::Isa::kAvx2) return LitGridAvx2;
#endif
  (void)isa;
  return LitGridBaseline;
}

/// The first index in [from, end) whose flag is not 0, or `end`: eight flags a word.
size_t NextFlagged(const uint8_t* flags, size_t from, size_t end) {
  size_t k = from;
  for (; k < end && k % 8 != 0; ++k) {
    if (flags[k]) return k;
  }
  for (; k + 8 <= end; k += 8) {
    uint64_t word;
    std::memcpy(&word, flags + k, sizeof word);
    if (word != 0) break;
  }
  for (; k < end; ++k) {
    if (flags[k]) return k;
  }
  return end;
}

}  // namespace

std::optional<tiles::ViewCap> SampleCap(const Eigen::Vector3d& x, const Eigen::Vector3d& o,
                                        double vossel_size_m, double pitch_rad) {
  const double patch_m = kSamplePatchM * vossel_size_m;
  const Eigen::Vector3d to = x - o;
  const double range = to.norm();
  if (!(range > 2.0 * patch_m)) return std::nullopt;
  tiles::ViewCap cap;
  cap.dir = to / range;
  cap.half_angle_rad = std::asin(patch_m / range) + pitch_rad;
  cap.near_m = range - patch_m;
  cap.far_m = range + patch_m;
  return cap;
}

std::vector<float> ComputeVisibility(const records::VosselGeometry& g, const DepthPanorama& depth,
                                     double tau_m, const std::vector<uint8_t>* only,
                                     int slope_pixels, bool shadow_by_cells) {
  // PCF samples over the vossel's patch: a 4×4 grid and the centre. 17 samples make V a
  // multiple of 1/17, which the record's 8-bit `vis` stores exactly (code 15·lit of 255), so no
  // V ≥ V_min test a profile can set flips between ingest and a reweight from disk (§7).
  constexpr int kGrid = 4;
  constexpr int kSamples = kGrid * kGrid + 1;
  std::vector<float> vis(g.size(), 0.0f);
  const double h = g.vossel_size_m;
  const Eigen::Matrix3d R_sensor_world = depth.pose.q_world_sensor.conjugate().toRotationMatrix();
  const int W = depth.size.width_px, H = depth.size.height_px;
  const double pitch_rad =
      std::max(geometry::AzimuthPitchRad(depth.size), geometry::ElevationPitchRad(depth.size));
  const double pixel_rad = slope_pixels * pitch_rad;
  // Shadow by reach cells (exact): a vossel whose every sample lies, beyond its tolerance,
  // farther than the farthest depth of each cell its patch can fall in fails every test, V = 0
  // without a test per sample. Taken when enough vossels are tested to pay for the cells' pass.
  constexpr int kCell = tiles::kReachBlockPx;
  const size_t tested =
      only == nullptr ? g.size() : size_t(std::count(only->begin(), only->end(), uint8_t{1}));
  std::optional<tiles::CapCells> grid;
  tiles::ReachRaster farthest;
  if (shadow_by_cells && tested >= kShadowByCellsMinVossels && W % kCell == 0 &&
      H % kCell == 0) {
    grid.emplace(geometry::EquirectSize{W / kCell, H / kCell}, depth.pose);
    farthest = tiles::ReachFromDepth(depth.depth_m, depth.size);
  }
  const double patch_m = kSamplePatchM * h;
  // The grid samples' offsets along the patch's tangents, sample a·kGrid + b at
  // ((a + ½)/kGrid − ½)·h and ((b + ½)/kGrid − ½)·h.
  std::array<double, kGrid * kGrid> offset_a, offset_b;
  for (int s = 0; s < kGrid * kGrid; ++s) {
    offset_a[s] = ((s / kGrid + 0.5) / kGrid - 0.5) * h;
    offset_b[s] = ((s % kGrid + 0.5) / kGrid - 0.5) * h;
  }
  const LitGridFn lit_grid = LitGridOn(memory::WidestIsa());
  // Whole chunks of kShadowChunk consecutive vossels (neighbours in the lattice's canonical
  // order) first: when the box of their frame centroids lies, beyond the largest tolerance,
  // behind the farthest depth of every cell its cap (grown by the patch, one pixel wider) can
  // fall in, each of its vossels' caps lies in that cap and its nearest sample's threshold
  // behind the box's, so each one's shadow-by-cells test below holds: V = 0 for all of them.
  constexpr size_t kShadowChunk = 64;
  auto chunk_in_shadow = [&](size_t begin, size_t end) {
    Eigen::Vector3d lo = Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity());
    Eigen::Vector3d hi = -lo;
    for (size_t k = begin; k != end; ++k) {
      if (only != nullptr && !(*only)[k]) continue;
      const Eigen::Vector3d x = g.FrameCentroid(k).cast<double>();
      lo = lo.cwiseMin(x);
      hi = hi.cwiseMax(x);
    }
    if (!(lo.x() <= hi.x())) return true;  // nothing tested
    tiles::ViewCap cap = tiles::CapOf({lo, hi}, depth.pose.o_world, patch_m);
    if (cap.everywhere || !(cap.near_m > 2.0 * patch_m)) return false;
    cap.half_angle_rad += pitch_rad;
    // Its vossels' largest tolerance: at its far side, cosθ at its floor.
    const double behind_m = cap.near_m - patch_m -
                            SlopeScaledToleranceM(tau_m, cap.far_m, pixel_rad,
                                                  geometry::kCosIncidenceMin);
    return !grid->Reaches(cap, farthest.max_depth_m, behind_m);
  };
  tbb::parallel_for(tbb::blocked_range<size_t>(0, g.size(), 1024), [&](const tbb::blocked_range<size_t>& r) {
    size_t chunk_tested = std::numeric_limits<size_t>::max();  // the chunk last tested whole
    for (size_t k = r.begin(); k != r.end(); ++k) {
      if (only != nullptr && !(*only)[k]) {
        // A revisit flags a few of the project's vossels: its unflagged runs are passed over
        // eight flags at a time (one pass a byte was most of a revisit's call on the twelfth
        // corridor scan, perf 2026-12-07).
        k = NextFlagged(only->data(), k + 1, r.end()) - 1;
        continue;
      }
      // A chunk entered (at its first flagged vossel: those before it are not tested).
      if (grid && k / kShadowChunk != chunk_tested) {
        chunk_tested = k / kShadowChunk;
        const size_t end = std::min(r.end(), (chunk_tested + 1) * kShadowChunk);
        if (chunk_in_shadow(k, end)) {
          k = end - 1;  // V = 0 for the chunk
          continue;
        }
      }
      const Eigen::Vector3d x = g.FrameCentroid(k).cast<double>();
      Eigen::Vector3d n = g.FrameNormal(k).cast<double>();
      const Eigen::Vector3d to_sensor = depth.pose.o_world - x;
      if (to_sensor.squaredNorm() == 0.0) continue;
      if (n.squaredNorm() < 0.5) n = to_sensor.normalized();
      const double tolerance_m = VosselToleranceM(tau_m, to_sensor, n, pixel_rad);
      const std::optional<tiles::ViewCap> cap =
          grid ? SampleCap(x, depth.pose.o_world, h, pitch_rad) : std::nullopt;
      if (cap) {
        const double behind_m = cap->near_m - tolerance_m;  // the nearest sample's threshold
        if (!grid->Reaches(*cap, farthest.max_depth_m, behind_m)) continue;  // V = 0
      }
      const Eigen::Vector3d t1 = geometry::AnyTangent(n), t2 = n.cross(t1);
      // One sample: the point at offsets (sa, sb) of the patch, lit where the depth panorama
      // holds nothing nearer than its range less the tolerance.
      const auto lit_at = [&](double sa, double sb) {
        const Eigen::Vector3d p_s = R_sensor_world * (x + sa * t1 + sb * t2 - depth.pose.o_world);
        const double range = p_s.norm();
        const Eigen::Vector2d uv = geometry::EquirectProject(p_s, depth.size);
        const int i = geometry::WrapColumn(int(std::floor(uv.x())), W);
        const int j = std::clamp(int(std::floor(uv.y())), 0, H - 1);
        return depth.At(i, j) >= range - tolerance_m ? 1 : 0;
      };
      PatchFrame f;
      for (int c = 0; c < 3; ++c) {
        f.x[c] = x[c];
        f.t1[c] = t1[c];
        f.t2[c] = t2[c];
        f.o[c] = depth.pose.o_world[c];
        for (int q = 0; q < 3; ++q) f.R[3 * c + q] = R_sensor_world(c, q);
      }
      int lit = lit_grid(offset_a.data(), offset_b.data(), f, depth.depth_m.data(), W, H,
                         tolerance_m);
      if (lit < 0) {  // a direction the lanes leave to the scalar code
        lit = 0;
        for (int s = 0; s < kGrid * kGrid; ++s) lit += lit_at(offset_a[s], offset_b[s]);
      }
      lit += lit_at(0.0, 0.0);  // the centre
      vis[k] = float(lit) / float(kSamples);
    }
  });
  return vis;
}

}  // namespace vasl::ingest

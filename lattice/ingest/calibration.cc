// Calibration health, VASL-MODEL §2.3 (calibration.h has the method and its choices).
#include "lattice/ingest/calibration.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstring>
#include <limits>
#include <memory>
#include <numeric>

#include <Eigen/SVD>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_reduce.h>

#include "absl/strings/str_format.h"
#include "lattice/ingest/sample.h"
#include "lattice/memory/isa.h"
#include "lattice/memory/lanes.h"

namespace vasl::ingest {
namespace {

using records::CalibrationHealth;
using Verdict = records::CalibrationHealth::Verdict;

constexpr float kEmpty = std::numeric_limits<float>::quiet_NaN();
constexpr uint64_t kNoReturn = std::numeric_limits<uint64_t>::max();
constexpr double kFillWanted = 0.9;   // share of the cells around returns that must hold one
constexpr int kScaleLevels = 6;       // analysis scales tried: s0, 2·s0, … 32·s0
constexpr double kMaxDepthSpread = 0.1;  // a patch's range spread over its centre's: no edge
constexpr double kMinEigenRatio = 0.1;   // smaller over larger structure-tensor eigenvalue
constexpr double kLevelWithNearest = 0.05;  // a return within 5 % of a cell's nearest counts
constexpr float kMinWeight = 0.25f;      // least bilinear weight a cell's LiDAR value rests on
constexpr double kMinCurvature = 0.005;  // least fall of the correlation a cell off its peak
constexpr int kNeighbours = 6;           // matches a match is compared with
constexpr double kConsistentCells = 1.0; // how far a match may stray from its neighbours' median
constexpr size_t kRoundTripSample = 100'000;  // returns the round trip is measured on

// Mean and 95th percentile of the finite values of v; (0, 0) when there is none.
std::pair<double, double> MeanP95(std::vector<double> v) {
  v.erase(std::remove_if(v.begin(), v.end(), [](double x) { return !std::isfinite(x); }), v.end());
  if (v.empty()) return {0.0, 0.0};
  const double mean = std::accumulate(v.begin(), v.end(), 0.0) / double(v.size());
  const size_t k = size_t(std::ceil(0.95 * double(v.size()))) - 1;
  std::nth_element(v.begin(), v.begin() + ptrdiff_t(k), v.end());
  return {mean, v[k]};
}

float Luminance709(const float* rgb) { return 0.2126f * rgb[0] + 0.7152f * rgb[1] + 0.0722f * rgb[2]; }

// The camera's view of the LiDAR's returns.
class View {
 public:
  View(const LidarSource& lidar, const CameraSource& camera, const ImageProjection& projection)
      : lidar_(lidar), camera_(camera), projection_(projection) {}

  size_t size() const { return lidar_.point_count(); }

  // Return i as the camera sees it: its world point, continuous pixel coordinates and range
  // from the camera. False when it is no return (0, 0, 0), behind the camera or off its image.
  bool Project(size_t i, Eigen::Vector3d* x, Eigen::Vector2d* uv, double* r) const {
    const float* p = &lidar_.xyz_sensor_m[3 * i];
    if (p[0] == 0.0f && p[1] == 0.0f && p[2] == 0.0f) return false;
    *x = lidar_.pose.SensorToWorld(Eigen::Vector3d(p[0], p[1], p[2]));
    const Eigen::Vector3d d = *x - camera_.pose.o_world;
    *r = d.norm();
    if (!(*r > 0.0) || !std::isfinite(*r)) return false;
    const std::optional<Eigen::Vector2d> px = projection_.Project(camera_.pose.DirectionToSensor(d));
    if (!px || !projection_.Inside(*px)) return false;
    *uv = *px;
    return true;
  }

  // The world point at range r along the ray through pixel coordinates uv (§2.3's lift).
  Eigen::Vector3d Lift(const Eigen::Vector2d& uv, double r) const {
    return camera_.pose.o_world + r * camera_.pose.DirectionToWorld(projection_.Unproject(uv));
  }

 private:
  const LidarSource& lidar_;
  const CameraSource& camera_;
  const ImageProjection& projection_;
};

// A raster of analysis cells, s × s camera pixels each; columns wrap for a panorama.
struct Cells {
  int s = 1, width = 0, height = 0;
  bool wrap = false;
  int Column(double u) const { return std::clamp(int(std::floor(u / s)), 0, width - 1); }
  int Row(double v) const { return std::clamp(int(std::floor(v / s)), 0, height - 1); }
  // Index of cell (x, y); -1 off the raster (x wraps for a panorama).
  int64_t At(int x, int y) const {
    if (y < 0 || y >= height) return -1;
    if (wrap) x = ((x % width) + width) % width;
    if (x < 0 || x >= width) return -1;
    return int64_t(y) * width + x;
  }
};

Cells CellsAt(int s, int W, int H, bool wrap) {
  return Cells{s, (W + s - 1) / s, (H + s - 1) / s, wrap};
}

// Key of a return in a cell's z-buffer: its range's bits (a positive float's bits order as the
// float does), then its index, so that the smallest key is the nearest return.
uint64_t NearestKey(double r, size_t i) {
  const float rf = float(r);
  uint32_t bits;
  std::memcpy(&bits, &rf, 4);
  return (uint64_t{bits} << 32) | uint64_t(i);
}

// The returns splatted into the cells of one analysis scale, nearest return per cell.
struct Splat {
  Cells cells;
  // NearestKey per cell, kNoReturn for none. An array whose cells start unset (a C++17 atomic's
  // default constructor leaves it so): the finest scale is set in parallel and the coarser
  // ones are written whole, where a vector would first zero them all on one thread (85 MB for
  // a 4096-pixel panorama).
  std::unique_ptr<std::atomic<uint64_t>[]> nearest;
  size_t size() const { return size_t(cells.width) * size_t(cells.height); }
};

// A return as the camera sees it: continuous pixel coordinates and range; r NaN when unseen.
struct Projected {
  double u, v, r;
};

// The returns splatted at every candidate scale (s0 the smallest scale that keeps the raster
// within max_width cells, then 2·s0, … 32·s0: the finest splatted, each coarser one pooled
// from the one before, exactly as a splat of its own would fill it); the index of the
// smallest scale whose cells the returns fill: where, of the cells within one of a return,
// kFillWanted hold one (else the coarsest). `in_view`: the returns the camera sees;
// `projected`: every return as View::Project gives it (range NaN: not seen), so that the
// LiDAR image is made without projecting the returns again.
size_t SplatAndChoose(const View& view, int W, int H, bool wrap, int max_width,
                      std::vector<Splat>* levels, int64_t* in_view,
                      std::vector<Projected>* projected) {
  int s0 = 1;
  while ((W + s0 - 1) / s0 > max_width) s0 *= 2;
  *levels = std::vector<Splat>(kScaleLevels);
  for (int l = 0; l < kScaleLevels; ++l) {
    Splat& level = (*levels)[l];
    level.cells = CellsAt(s0 << l, W, H, wrap);
    level.nearest.reset(new std::atomic<uint64_t>[level.size()]);
  }
  // The returns go into the finest scale's cells (a cell per pixel of a large image: 8 M of
  // them, set in parallel); the coarser ones are made from it below.
  std::atomic<uint64_t>* finest = levels->front().nearest.get();
  tbb::parallel_for(tbb::blocked_range<size_t>(0, levels->front().size(), 1 << 16),
                    [&finest](const tbb::blocked_range<size_t>& r) {
                      for (size_t k = r.begin(); k != r.end(); ++k) {
                        finest[k].store(kNoReturn, std::memory_order_relaxed);
                      }
                    });
  std::atomic<int64_t> seen_total{0};
  projected->resize(view.size());
  tbb::parallel_for(tbb::blocked_range<size_t>(0, view.size(), 1 << 14), [&](const auto& range) {
    Eigen::Vector3d x;
    Eigen::Vector2d uv;
    double r;
    int64_t seen_here = 0;
    for (size_t i = range.begin(); i != range.end(); ++i) {
      if (i > std::numeric_limits<uint32_t>::max() || !view.Project(i, &x, &uv, &r)) {
        (*projected)[i] = {0.0, 0.0, std::numeric_limits<double>::quiet_NaN()};
        continue;
      }
      (*projected)[i] = {uv.x(), uv.y(), r};
      ++seen_here;
      const uint64_t key = NearestKey(r, i);
      Splat& finest = levels->front();
      const Cells& c = finest.cells;
      std::atomic<uint64_t>& slot = finest.nearest[size_t(c.At(c.Column(uv.x()), c.Row(uv.y())))];
      uint64_t seen = slot.load(std::memory_order_relaxed);
      while (key < seen && !slot.compare_exchange_weak(seen, key, std::memory_order_relaxed)) {
      }
    }
    seen_total += seen_here;
  });
  *in_view = seen_total.load();
  // Each coarser scale's nearest return per cell: the nearest of the 2×2 finer cells it covers
  // (floor(u / 2s) = floor(floor(u / s) / 2), and the clamp to the last cell halves alike).
  for (size_t l = 1; l < levels->size(); ++l) {
    const Splat& fine = (*levels)[l - 1];
    Splat& coarse = (*levels)[l];
    const int fw = fine.cells.width, fh = fine.cells.height, cw = coarse.cells.width;
    tbb::parallel_for(tbb::blocked_range<int>(0, coarse.cells.height),
                      [&](const tbb::blocked_range<int>& rows) {
      for (int y = rows.begin(); y != rows.end(); ++y) {
        for (int x = 0; x < cw; ++x) {
          uint64_t nearest = kNoReturn;
          for (int fy = 2 * y; fy < std::min(2 * y + 2, fh); ++fy) {
            for (int fx = 2 * x; fx < std::min(2 * x + 2, fw); ++fx) {
              nearest = std::min(
                  nearest, fine.nearest[size_t(fy) * size_t(fw) + size_t(fx)].load(
                               std::memory_order_relaxed));
            }
          }
          coarse.nearest[size_t(y) * size_t(cw) + size_t(x)].store(nearest,
                                                                    std::memory_order_relaxed);
        }
      }
    });
  }
  for (size_t l = 0; l < levels->size(); ++l) {
    const Splat& level = (*levels)[l];
    const Cells& c = level.cells;
    // A cell is near a return when one of the 3×3 cells about it (columns wrapping on a
    // panorama) holds one: the OR of a row's cell and its two neighbours, then of three such
    // rows, in flat passes over bytes (a cell per pixel at the finest scale of a large image).
    const size_t w = size_t(c.width);
    std::vector<uint8_t> filled(w * size_t(c.height)), across(filled.size());
    tbb::parallel_for(tbb::blocked_range<int>(0, c.height), [&](const tbb::blocked_range<int>& rows) {
      for (int y = rows.begin(); y != rows.end(); ++y) {
        const size_t row = size_t(y) * w;
        for (size_t x = 0; x < w; ++x) {
          filled[row + x] = level.nearest[row + x].load(std::memory_order_relaxed) != kNoReturn;
        }
        const uint8_t* f = &filled[row];
        uint8_t* a = &across[row];
        for (size_t x = 1; x + 1 < w; ++x) a[x] = f[x - 1] | f[x] | f[x + 1];
        const auto at = [&](int64_t x) -> uint8_t {  // 0 off the raster
          const int64_t k = c.At(int(x), y);
          return k < 0 ? 0 : filled[size_t(k)];
        };
        for (size_t x : {size_t{0}, w - 1}) a[x] = at(int64_t(x) - 1) | f[x] | at(int64_t(x) + 1);
      }
    });
    using Counts = std::pair<int64_t, int64_t>;  // cells with a return, cells near one
    const Counts counts = tbb::parallel_reduce(
        tbb::blocked_range<int>(0, c.height), Counts{0, 0},
        [&](const tbb::blocked_range<int>& rows, Counts n) {
          for (int y = rows.begin(); y != rows.end(); ++y) {
            const uint8_t* f = &filled[size_t(y) * w];
            const uint8_t* mid = &across[size_t(y) * w];
            const uint8_t* up = y > 0 ? mid - w : nullptr;
            const uint8_t* down = y + 1 < c.height ? mid + w : nullptr;
            int64_t with = 0, near = 0;
            for (size_t x = 0; x < w; ++x) {
              with += f[x];
              near += mid[x] | (up != nullptr ? up[x] : 0) | (down != nullptr ? down[x] : 0);
            }
            n.first += with;
            n.second += near;
          }
          return n;
        },
        [](Counts a, Counts b) { return Counts{a.first + b.first, a.second + b.second}; });
    if (counts.second > 0 && double(counts.first) >= kFillWanted * double(counts.second)) return l;
  }
  return levels->size() - 1;
}

// One textured LiDAR patch: its centre cell and structure.
struct Feature {
  int x = 0, y = 0;
  double strength = 0.0;  // the structure tensor's smaller eigenvalue
};

// The correlation of n pairs (a, b) from their sums Σa, Σb, Σa², Σb², Σab; -inf when n < min_n
// or either side is flat.
double NccOfSums(double sa, double sb, double saa, double sbb, double sab, size_t n,
                 size_t min_n) {
  if (n < min_n) return -std::numeric_limits<double>::infinity();
  const double va = saa - sa * sa / n, vb = sbb - sb * sb / n;
  if (!(va > 1e-12) || !(vb > 1e-12)) return -std::numeric_limits<double>::infinity();
  return (sab - sa * sb / n) / std::sqrt(va * vb);
}

// The (2R+1)² values of raster img around (cx, cy), NaN off the raster.
void Patch(const std::vector<float>& img, const Cells& c, int cx, int cy, int R,
           std::vector<float>* out) {
  out->resize(size_t(2 * R + 1) * (2 * R + 1));
  size_t k = 0;
  for (int j = -R; j <= R; ++j)
    for (int i = -R; i <= R; ++i) {
      const int64_t at = c.At(cx + i, cy + j);
      (*out)[k++] = at < 0 ? kEmpty : img[size_t(at)];
    }
}

// The best NCC of `templ` against `img` over shifts within ±S of (cx, cy): the shift, the
// correlation grid ((2S+1)², row-major) and its peak value.
struct Search {
  int bx = 0, by = 0;
  double best = -std::numeric_limits<double>::infinity();
  std::vector<double> grid;
};
/// W doubles to a vector (GCC's vector extensions: SSE2's width, or AVX2's; or one), and W
/// floats.
template <int W>
using Vectors = memory::Lanes<W>;

/// W consecutive floats at `p`, as doubles, into `out`.
template <int W>
[[gnu::always_inline]] inline void LoadDoubles(const float* p, typename Vectors<W>::Doubles& out) {
  if constexpr (W == 1) {
    out = *p;
  } else {
    typename Vectors<W>::Floats f;
    std::memcpy(&f, p, sizeof f);
    out = __builtin_convertvector(f, typename Vectors<W>::Doubles);
  }
}

// The correlations (NccOfSums) of `templ` against the window at the L shifts (dx0 + l, dy):
// each lane sums its own pairs in the template's row-major order, so that interleaving the
// lanes, which keeps many sums in flight where one shift kept three, gives the same bits.
// kWhole: the window holds no NaN, and the template's finite cells are `at` (offsets into the
// window), their sums sa and saa. Otherwise `window` has its NaNs as zeros and `finite` is 1
// where it had a value, 0 where not: a pair with an empty cell then adds ±0 to each sum, which
// leaves it as it was (a sum of finite values starting at +0 is never −0), as skipping it did.
template <int W, int L, bool kWhole>
[[gnu::always_inline]] inline void CorrelateLanes(const float* templ, const float* window,
                                                  const float* finite, int patch, int span,
                                                  int dx0, int dy, const std::vector<size_t>& at,
                                                  const std::vector<float>& a, double sa_whole,
                                                  double saa_whole, size_t min_n, double* out) {
  static_assert(L % W == 0, "lanes come in whole vectors");
  using Doubles = typename Vectors<W>::Doubles;
  constexpr int kV = L / W;
  Doubles sa[kV] = {}, sb[kV] = {}, saa[kV] = {}, sbb[kV] = {}, sab[kV] = {}, n[kV] = {};
  const auto lane = [](const Doubles* v, int l) {
    if constexpr (W == 1) {
      return v[l];
    } else {
      return double(v[l / W][l % W]);
    }
  };
  const size_t origin = size_t(dy) * span + dx0;
  if constexpr (kWhole) {
    for (size_t k = 0; k < at.size(); ++k) {
      const float* b = window + origin + at[k];
      const double ak = a[k];
      for (int v = 0; v < kV; ++v) {
        Doubles t;
        LoadDoubles<W>(b + W * v, t);
        sb[v] += t, sbb[v] += t * t, sab[v] += ak * t;
      }
    }
    for (int l = 0; l < L; ++l) {
      out[l] = NccOfSums(sa_whole, lane(sb, l), saa_whole, lane(sbb, l), lane(sab, l), at.size(),
                         min_n);
    }
  } else {
    for (int j = 0; j < patch; ++j)
      for (int i = 0; i < patch; ++i) {
        const float ak = templ[size_t(j) * patch + i];
        if (std::isnan(ak)) continue;
        const double a1 = ak, a2 = double(ak) * ak;
        const size_t offset = origin + size_t(j) * span + i;
        for (int v = 0; v < kV; ++v) {
          Doubles t, pair;
          LoadDoubles<W>(window + offset + W * v, t);
          LoadDoubles<W>(finite + offset + W * v, pair);
          sa[v] += a1 * pair, sb[v] += t, saa[v] += a2 * pair, sbb[v] += t * t;
          sab[v] += a1 * t, n[v] += pair;
        }
      }
    for (int l = 0; l < L; ++l) {
      out[l] = NccOfSums(lane(sa, l), lane(sb, l), lane(saa, l), lane(sbb, l), lane(sab, l),
                         size_t(lane(n, l)), min_n);
    }
  }
}

/// CorrelationGrid's window, prepared: with holes, `filled` and `finite` (CorrelateLanes);
/// whole, the template's finite cells `at`, their values `a` and sums sa, saa.
struct Correlation {
  const float* templ = nullptr;
  const float* window = nullptr;  ///< `filled` with holes
  const float* finite = nullptr;  ///< null when whole
  int patch = 0, span = 0, side = 0;
  std::vector<size_t> at;
  std::vector<float> a;
  double sa = 0, saa = 0;
  size_t min_n = 0;
};

/// Every shift's correlation into `grid`, row by row, kWholeLanes or kHoleLanes shifts at once
/// in vectors of W doubles.
template <int W, int kWholeLanes, int kHoleLanes>
[[gnu::always_inline]] inline void CorrelateRows(const Correlation& c, double* grid) {
  for (int dy = 0; dy < c.side; ++dy) {
    double* row = grid + size_t(dy) * c.side;
    int dx = 0;
    if (c.finite == nullptr) {
      for (; dx + kWholeLanes <= c.side; dx += kWholeLanes) {
        CorrelateLanes<W, kWholeLanes, true>(c.templ, c.window, nullptr, c.patch, c.span, dx,
                                             dy, c.at, c.a, c.sa, c.saa, c.min_n, row + dx);
      }
      for (; dx < c.side; ++dx) {
        CorrelateLanes<1, 1, true>(c.templ, c.window, nullptr, c.patch, c.span, dx, dy, c.at, c.a,
                                   c.sa, c.saa, c.min_n, row + dx);
      }
    } else {
      for (; dx + kHoleLanes <= c.side; dx += kHoleLanes) {
        CorrelateLanes<W, kHoleLanes, false>(c.templ, c.window, c.finite, c.patch, c.span, dx,
                                             dy, c.at, c.a, c.sa, c.saa, c.min_n, row + dx);
      }
      for (; dx < c.side; ++dx) {
        CorrelateLanes<1, 1, false>(c.templ, c.window, c.finite, c.patch, c.span, dx, dy, c.at,
                                    c.a, c.sa, c.saa, c.min_n, row + dx);
      }
    }
  }
}

// As many lanes as the registers hold the sums of: three a lane whole, six with holes.
void CorrelateRowsBaseline(const Correlation& c, double* grid) {
  CorrelateRows<2, 8, 4>(c, grid);
}
#if VASL_ISA_VARIANTS
[[gnu::target("avx2")]] void CorrelateRowsAvx2(const Correlation& c, double* grid) {
  CorrelateRows<4, 8, 8>(c, grid);
}
#endif

}  // namespace

namespace internal {

std::vector<double> CorrelationGrid(const std::vector<float>& templ,
                                    const std::vector<float>& window, int R, int S,
                                    size_t min_n) {
  Correlation c;
  c.patch = 2 * R + 1;
  c.span = 2 * (R + S) + 1;
  c.side = 2 * S + 1;
  c.templ = templ.data();
  c.min_n = min_n;
  // A window without holes (the camera image's, away from a pinhole image's edges): every
  // shift pairs the template's finite cells, so their sums are taken once and each shift sums
  // only its own side, in the same order (the same correlations, bit for bit).
  const bool whole =
      std::none_of(window.begin(), window.end(), [](float v) { return std::isnan(v); });
  std::vector<float> filled, finite;
  if (whole) {
    c.window = window.data();
    c.finite = nullptr;
    for (int j = 0; j < c.patch; ++j)
      for (int i = 0; i < c.patch; ++i) {
        const float t = templ[size_t(j) * c.patch + i];
        if (std::isnan(t)) continue;
        c.sa += t, c.saa += double(t) * t;
        c.at.push_back(size_t(j) * c.span + i);
        c.a.push_back(t);
      }
  } else {
    filled.resize(window.size());
    finite.resize(window.size());
    for (size_t k = 0; k < window.size(); ++k) {
      finite[k] = std::isnan(window[k]) ? 0.0f : 1.0f;
      filled[k] = std::isnan(window[k]) ? 0.0f : window[k];
    }
    c.window = filled.data();
    c.finite = finite.data();
  }
  std::vector<double> grid(size_t(c.side) * c.side);
#if VASL_ISA_VARIANTS
  if (memory::WidestIsa() >= memory::Isa::kAvx2) {
    CorrelateRowsAvx2(c, grid.data());
    return grid;
  }
#endif
  CorrelateRowsBaseline(c, grid.data());
  return grid;
}

}  // namespace internal

namespace {

Search SearchAround(const std::vector<float>& templ, const std::vector<float>& img,
                    const Cells& c, int cx, int cy, int R, int S, size_t min_n) {
  const int side = 2 * S + 1, span = 2 * (R + S) + 1;
  std::vector<float> window(size_t(span) * span);
  for (int j = 0; j < span; ++j)
    for (int i = 0; i < span; ++i) {
      const int64_t at = c.At(cx - R - S + i, cy - R - S + j);
      window[size_t(j) * span + i] = at < 0 ? kEmpty : img[size_t(at)];
    }
  Search out;
  out.grid = internal::CorrelationGrid(templ, window, R, S, min_n);
  for (int dy = 0; dy < side; ++dy)
    for (int dx = 0; dx < side; ++dx) {
      const double v = out.grid[size_t(dy) * side + dx];
      if (v > out.best) out.best = v, out.bx = dx - S, out.by = dy - S;
    }
  return out;
}

// Subpixel offset of a parabola through (−1, a), (0, b), (+1, c); nullopt unless b is a peak.
std::optional<double> ParabolaPeak(double a, double b, double c) {
  const double curvature = a - 2.0 * b + c;
  if (!std::isfinite(curvature) || !(curvature < 0.0)) return std::nullopt;
  return std::clamp(0.5 * (a - c) / curvature, -0.5, 0.5);
}

}  // namespace

CalibrationHealth CheckCalibration(const LidarSource& lidar, const CameraSource& camera,
                                   const LinearImage& image, const CalibrationSettings& cfg) {
  CalibrationHealth out;
  out.lidar_source = lidar.id;
  const int W = image.width_px, H = image.height_px;
  const size_t N = lidar.point_count();
  const ImageProjection projection = ProjectionOf(camera, W, H);
  const View view(lidar, camera, projection);
  const bool wrap = !camera.pinhole;

  // The LiDAR's texture: intensity when it varies, else the returns' colour luminance.
  const float* intensity = nullptr;
  if (lidar.intensity.size() == N && N > 0) {
    const auto [lo, hi] = std::minmax_element(lidar.intensity.begin(), lidar.intensity.end());
    if (*hi > *lo) intensity = lidar.intensity.data();
  }
  const bool colour = intensity == nullptr && lidar.rgb.size() == 3 * N && N > 0;
  const auto texture = [&](size_t i) {
    return intensity ? intensity[i] : Luminance709(&lidar.rgb[3 * i]);
  };

  // 1. The returns splatted into analysis cells at every candidate scale (nearest per cell),
  // and the scale they fill chosen.
  std::vector<Splat> levels;
  int64_t in_view = 0;
  std::vector<Projected> projected;
  const size_t level =
      SplatAndChoose(view, W, H, wrap, cfg.max_analysis_width, &levels, &in_view, &projected);
  out.points_in_view = in_view;
  if (in_view == 0) {
    out.note = "the camera sees none of the scan's returns";
    return out;
  }

  // 2. The round trip, on an even sample of the returns.
  const size_t stride = std::max<size_t>(1, N / kRoundTripSample);
  std::vector<double> roundtrip((N + stride - 1) / stride, std::nan(""));
  tbb::parallel_for(tbb::blocked_range<size_t>(0, roundtrip.size(), 1 << 12), [&](const auto& range) {
    Eigen::Vector3d x;
    Eigen::Vector2d uv;
    double r;
    for (size_t k = range.begin(); k != range.end(); ++k) {
      if (view.Project(k * stride, &x, &uv, &r)) roundtrip[k] = (x - view.Lift(uv, r)).norm();
    }
  });
  std::tie(out.roundtrip_mean_m, out.roundtrip_p95_m) = MeanP95(std::move(roundtrip));
  if (!intensity && !colour) {
    out.note = "the LiDAR has neither intensity nor colour to match against the image";
    return out;
  }

  // 3. The LiDAR and camera images in the chosen cells.
  const Cells cells = levels[level].cells;
  const std::atomic<uint64_t>* nearest = levels[level].nearest.get();
  out.cell_px = cells.s;
  const size_t n_cells = levels[level].size();

  // The LiDAR image at the cells' centres: each return's texture spread bilinearly over the four
  // centres around it, into the cells whose nearest return it is level with (not a farther
  // surface seen past an edge). Nearest-return splatting would shift each cell's value by up to
  // half a cell, and the matches with it.
  std::vector<float> range_img(n_cells, kEmpty);
  tbb::parallel_for(size_t{0}, n_cells, [&](size_t c) {
    const uint64_t key = nearest[c].load(std::memory_order_relaxed);
    if (key == kNoReturn) return;
    const uint32_t bits = uint32_t(key >> 32);
    std::memcpy(&range_img[c], &bits, 4);
  });
  // Each return's texture goes to the (up to) four cells about it. The sums are taken row
  // band by row band, each band's returns in the order of their index, so that every cell adds
  // its contributions in one order whatever the threads: the figures are reproducible.
  std::vector<float> sum(n_cells, 0.0f), weight(n_cells, 0.0f);
  {
    constexpr int kBandRows = 8;
    const int bands = (cells.height + kBandRows - 1) / kBandRows;
    // The band of a return's upper cell row and of its lower one (-1: off the raster).
    const auto bands_of = [&](const Projected& p) -> std::pair<int, int> {
      if (std::isnan(p.r)) return {-1, -1};
      const int iy = int(std::floor(p.v / cells.s - 0.5));
      const int upper = iy >= 0 && iy < cells.height ? iy / kBandRows : -1;
      const int lower = iy + 1 >= 0 && iy + 1 < cells.height ? (iy + 1) / kBandRows : -1;
      return {upper, lower == upper ? -1 : lower};
    };
    // A counting sort of the returns into bands, over fixed chunks of them.
    constexpr size_t kChunk = size_t(1) << 16;
    const size_t chunks = (N + kChunk - 1) / kChunk;
    std::vector<uint32_t> count(chunks * size_t(bands), 0);
    tbb::parallel_for(size_t{0}, chunks, [&](size_t ch) {
      uint32_t* n = &count[ch * size_t(bands)];
      for (size_t i = ch * kChunk; i < std::min(N, (ch + 1) * kChunk); ++i) {
        const auto [a, b] = bands_of(projected[i]);
        if (a >= 0) ++n[a];
        if (b >= 0) ++n[b];
      }
    });
    std::vector<size_t> band_begin(size_t(bands) + 1, 0), at(count.size());
    size_t total = 0;
    for (int b = 0; b < bands; ++b) {
      band_begin[size_t(b)] = total;
      for (size_t ch = 0; ch < chunks; ++ch) {
        at[ch * size_t(bands) + size_t(b)] = total;
        total += count[ch * size_t(bands) + size_t(b)];
      }
    }
    band_begin[size_t(bands)] = total;
    std::vector<uint32_t> order(total);
    tbb::parallel_for(size_t{0}, chunks, [&](size_t ch) {
      size_t* next = &at[ch * size_t(bands)];
      for (size_t i = ch * kChunk; i < std::min(N, (ch + 1) * kChunk); ++i) {
        const auto [a, b] = bands_of(projected[i]);
        if (a >= 0) order[next[a]++] = uint32_t(i);
        if (b >= 0) order[next[b]++] = uint32_t(i);
      }
    });
    tbb::parallel_for(0, bands, [&](int b) {
      const int row_begin = b * kBandRows, row_end = std::min(cells.height, row_begin + kBandRows);
      for (size_t q = band_begin[size_t(b)]; q < band_begin[size_t(b) + 1]; ++q) {
        const size_t i = order[q];
        const auto [u, v, r] = projected[i];
        const double fx = u / cells.s - 0.5, fy = v / cells.s - 0.5;
        const int ix = int(std::floor(fx)), iy = int(std::floor(fy));
        const double ax = fx - ix, ay = fy - iy;
        const float t = texture(i);
        for (int j = 0; j <= 1; ++j) {
          if (iy + j < row_begin || iy + j >= row_end) continue;  // another band's row
          for (int k = 0; k <= 1; ++k) {
            const int64_t c = cells.At(ix + k, iy + j);
            if (c < 0 || std::isnan(range_img[size_t(c)])) continue;
            if (r > (1.0 + kLevelWithNearest) * range_img[size_t(c)]) continue;
            const float w = float((k ? ax : 1.0 - ax) * (j ? ay : 1.0 - ay));
            sum[size_t(c)] += w * t;
            weight[size_t(c)] += w;
          }
        }
      }
    });
  }
  std::vector<Projected>().swap(projected);
  std::vector<float> lidar_img(n_cells, kEmpty), camera_img(n_cells, kEmpty);
  tbb::parallel_for(tbb::blocked_range<int>(0, cells.height), [&](const tbb::blocked_range<int>& rows) {
    for (int y = rows.begin(); y != rows.end(); ++y) {
      for (int x = 0; x < cells.width; ++x) {
        const size_t c = size_t(y) * cells.width + x;
        const float w = weight[c];
        if (w >= kMinWeight) lidar_img[c] = sum[c] / w;
        double total = 0.0;
        int n = 0;
        bool covered = true;  // a cell the image does not wholly cover (alpha) is a hole
        for (int j = y * cells.s; j < std::min(H, (y + 1) * cells.s); ++j)
          for (int i = x * cells.s; i < std::min(W, (x + 1) * cells.s); ++i) {
            const size_t p = size_t(j) * W + i;
            const float* px = &image.pixels[p * image.channels];
            total += image.channels >= 3 ? Luminance709(px) : px[0];
            covered = covered && (image.alpha.empty() || image.alpha[p] == 1.0f);
            ++n;
          }
        camera_img[c] = n && covered ? float(total / n) : kEmpty;
      }
    }
  });

  // 4. Textured patches: candidates on a grid of R + 1 cells whose whole search window lies on
  // the image (a panorama's columns wrap).
  const int R = cfg.patch_radius, S = cfg.search_radius;
  const size_t patch_cells = size_t(2 * R + 1) * (2 * R + 1);
  double global_std = 0.0;
  {
    double s1 = 0, s2 = 0;
    size_t n = 0;
    for (float v : lidar_img)
      if (!std::isnan(v)) s1 += v, s2 += double(v) * v, ++n;
    if (n > 1) global_std = std::sqrt(std::max(0.0, s2 / n - (s1 / n) * (s1 / n)));
  }
  const int margin = R + S + 1;
  const int x0 = wrap ? 0 : margin, x1 = wrap ? cells.width : cells.width - margin;
  std::vector<Feature> candidates;
  for (int y = margin; y < cells.height - margin; y += R + 1)
    for (int x = x0; x < x1; x += R + 1) candidates.push_back({x, y, 0.0});
  tbb::parallel_for(size_t{0}, candidates.size(), [&](size_t k) {
    Feature& f = candidates[k];
    const int64_t centre = cells.At(f.x, f.y);
    if (std::isnan(lidar_img[size_t(centre)])) return;
    const float r0 = range_img[size_t(centre)];
    size_t filled = 0;
    double s1 = 0, s2 = 0, sxx = 0, syy = 0, sxy = 0;
    for (int j = -R; j <= R; ++j)
      for (int i = -R; i <= R; ++i) {
        const int64_t c = cells.At(f.x + i, f.y + j);
        const float v = lidar_img[size_t(c)];
        if (std::isnan(v)) continue;
        if (std::abs(range_img[size_t(c)] - r0) > kMaxDepthSpread * r0) return;  // a depth edge
        ++filled, s1 += v, s2 += double(v) * v;
        const float l = lidar_img[size_t(cells.At(f.x + i - 1, f.y + j))];
        const float rt = lidar_img[size_t(cells.At(f.x + i + 1, f.y + j))];
        const float u = lidar_img[size_t(cells.At(f.x + i, f.y + j - 1))];
        const float d = lidar_img[size_t(cells.At(f.x + i, f.y + j + 1))];
        if (std::isnan(l) || std::isnan(rt) || std::isnan(u) || std::isnan(d)) continue;
        const double gx = 0.5 * (rt - l), gy = 0.5 * (d - u);
        sxx += gx * gx, syy += gy * gy, sxy += gx * gy;
      }
    if (filled < patch_cells * 4 / 5) return;
    const double var = s2 / filled - (s1 / filled) * (s1 / filled);
    if (!(std::sqrt(std::max(0.0, var)) > 0.02 * global_std)) return;
    const double half_trace = 0.5 * (sxx + syy);
    const double root = std::sqrt(std::max(0.0, half_trace * half_trace - (sxx * syy - sxy * sxy)));
    const double lo = half_trace - root, hi = half_trace + root;
    if (lo > 0.0 && lo >= kMinEigenRatio * hi) f.strength = lo;
  });
  std::sort(candidates.begin(), candidates.end(),
            [](const Feature& a, const Feature& b) { return a.strength > b.strength; });
  std::vector<Feature> features;
  for (const Feature& f : candidates) {
    if (!(f.strength > 0.0) || int(features.size()) >= cfg.max_features) break;
    const bool crowded = std::any_of(features.begin(), features.end(), [&](const Feature& g) {
      int dx = std::abs(g.x - f.x);
      if (wrap) dx = std::min(dx, cells.width - dx);
      return dx <= R && std::abs(g.y - f.y) <= R;
    });
    if (!crowded) features.push_back(f);
  }
  out.features = int64_t(features.size());

  // 5. Matches: forward (LiDAR patch in the camera image), subpixel, then back (the camera patch
  // found must search back to the LiDAR patch).
  struct Match {
    bool ok = false;
    double dx = 0, dy = 0;  // cells
  };
  std::vector<Match> matches(features.size());
  tbb::parallel_for(size_t{0}, features.size(), [&](size_t k) {
    const Feature& f = features[k];
    std::vector<float> templ, back;
    Patch(lidar_img, cells, f.x, f.y, R, &templ);
    const Search fwd = SearchAround(templ, camera_img, cells, f.x, f.y, R, S, patch_cells / 2);
    if (!(fwd.best >= cfg.min_ncc) || std::abs(fwd.bx) >= S || std::abs(fwd.by) >= S) return;
    const auto at = [&](int dx, int dy) { return fwd.grid[size_t(dy + S) * (2 * S + 1) + dx + S]; };
    const auto sx = ParabolaPeak(at(fwd.bx - 1, fwd.by), fwd.best, at(fwd.bx + 1, fwd.by));
    const auto sy = ParabolaPeak(at(fwd.bx, fwd.by - 1), fwd.best, at(fwd.bx, fwd.by + 1));
    if (!sx || !sy) return;
    // A peak flat along an axis does not locate the patch (an edge, or texture too smooth for
    // the cell): the correlation must fall by kMinCurvature a cell away on both axes.
    if (at(fwd.bx - 1, fwd.by) + at(fwd.bx + 1, fwd.by) - 2 * fwd.best > -kMinCurvature ||
        at(fwd.bx, fwd.by - 1) + at(fwd.bx, fwd.by + 1) - 2 * fwd.best > -kMinCurvature) {
      return;
    }
    Patch(camera_img, cells, f.x + fwd.bx, f.y + fwd.by, R, &back);
    const Search bwd = SearchAround(back, lidar_img, cells, f.x + fwd.bx, f.y + fwd.by, R, S,
                                    patch_cells / 2);
    if (std::abs(bwd.bx + fwd.bx) > 1 || std::abs(bwd.by + fwd.by) > 1) return;
    matches[k] = {true, fwd.bx + *sx, fwd.by + *sy};
  });

  // A miscalibrated camera shifts its image smoothly; a match that strays from the median shift
  // of its nearest matches by more than a cell found a look-alike patch, and is dropped.
  std::vector<size_t> found;
  for (size_t k = 0; k < matches.size(); ++k)
    if (matches[k].ok) found.push_back(k);
  std::vector<uint8_t> consistent(features.size(), 0);
  tbb::parallel_for(size_t{0}, found.size(), [&](size_t a) {
    const Feature& f = features[found[a]];
    std::vector<std::pair<double, size_t>> near;
    for (size_t b = 0; b < found.size(); ++b) {
      if (b == a) continue;
      double dx = std::abs(features[found[b]].x - f.x);
      if (wrap) dx = std::min(dx, cells.width - dx);
      near.emplace_back(std::hypot(dx, features[found[b]].y - f.y), found[b]);
    }
    const size_t n = std::min<size_t>(kNeighbours, near.size());
    if (n < 3) return;
    std::partial_sort(near.begin(), near.begin() + ptrdiff_t(n), near.end());
    std::vector<double> xs, ys;
    for (size_t b = 0; b < n; ++b) {
      xs.push_back(matches[near[b].second].dx);
      ys.push_back(matches[near[b].second].dy);
    }
    std::nth_element(xs.begin(), xs.begin() + ptrdiff_t(n / 2), xs.end());
    std::nth_element(ys.begin(), ys.begin() + ptrdiff_t(n / 2), ys.end());
    const Match& m = matches[found[a]];
    consistent[found[a]] = std::hypot(m.dx - xs[n / 2], m.dy - ys[n / 2]) <= kConsistentCells;
  });

  // The residuals of the matches, at the return of each patch's centre cell.
  std::vector<double> pixel, offset;
  Eigen::Matrix3d cross = Eigen::Matrix3d::Zero();
  for (size_t k = 0; k < features.size(); ++k) {
    if (!consistent[k]) continue;
    // x: the LiDAR's surface at the patch's centre (its nearest return's range there).
    const Eigen::Vector2d uv = (Eigen::Vector2d(features[k].x, features[k].y).array() + 0.5) * cells.s;
    const double r = range_img[size_t(cells.At(features[k].x, features[k].y))];
    const Eigen::Vector3d x = view.Lift(uv, r);
    const Eigen::Vector2d shift = Eigen::Vector2d(matches[k].dx, matches[k].dy) * cells.s;
    const Eigen::Vector2d m = uv + shift;
    pixel.push_back(shift.norm());
    offset.push_back((x - view.Lift(m, r)).norm());
    cross += projection.Unproject(uv) * projection.Unproject(m).transpose();
  }
  out.matched = int64_t(pixel.size());
  std::tie(out.pixel_mean_px, out.pixel_p95_px) = MeanP95(pixel);
  std::tie(out.offset_mean_m, out.offset_p95_m) = MeanP95(offset);
  if (pixel.size() >= 3) {  // 6. Kabsch: the rotation taking the projections onto the matches
    const Eigen::JacobiSVD<Eigen::Matrix3d> svd(cross, Eigen::ComputeFullU | Eigen::ComputeFullV);
    Eigen::Matrix3d fix = Eigen::Matrix3d::Identity();
    fix(2, 2) = (svd.matrixV() * svd.matrixU().transpose()).determinant() < 0 ? -1.0 : 1.0;
    const Eigen::Matrix3d rot = svd.matrixV() * fix * svd.matrixU().transpose();
    out.rotation_deg = std::acos(std::clamp(0.5 * (rot.trace() - 1.0), -1.0, 1.0)) * 180.0 / M_PI;
  }

  const double threshold = std::max(cfg.flag_p95_px, 0.75 * cells.s);
  if (out.matched < cfg.min_matches) {
    out.note = absl::StrFormat(
        "%d of %d textured patches matched (at least %d are needed): too little texture shared "
        "by the LiDAR's %s and the image, or the camera is far off its pose",
        out.matched, out.features, cfg.min_matches, intensity ? "intensity" : "colour");
  } else if (out.pixel_p95_px > threshold) {
    out.verdict = Verdict::kFlagged;
    out.note = absl::StrFormat(
        "the image lies %.2f px (95th percentile; mean %.2f px) off where the camera's pose "
        "projects the LiDAR, above the %.2g px allowed; the best-fitting rotation is %.2f deg: "
        "check the camera's pose and intrinsics before its colours are fused",
        out.pixel_p95_px, out.pixel_mean_px, threshold, out.rotation_deg);
  } else {
    out.verdict = Verdict::kOk;
  }
  return out;
}

}  // namespace vasl::ingest

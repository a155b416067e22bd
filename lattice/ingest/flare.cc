/// @file flare.cc
/// @brief Flare as per-pixel confidence (VASL-MODEL §9): bright sources and a parametric
///        veiling glare around each, measured from the image itself.
#include <algorithm>
#include <cmath>
#include <limits>
#include <numeric>
#include <vector>

#include <Eigen/Dense>
#include <tbb/blocked_range.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>

#include "lattice/ingest/artefacts.h"
#include "lattice/ingest/artefacts_internal.h"

namespace vasl::ingest {
namespace {

using internal::kAffectedShare;
using internal::kNoise;
using internal::kRingQuantile;
using internal::kSectors;

/// Most sources whose glare is measured, the largest blobs first *(choice)*.
constexpr size_t kMaxFlareSources = 32;
/// Rings between the bloom reach R_b and kOuterFactor·R_b, spaced evenly in log distance.
constexpr int kRings = 24;
constexpr double kOuterFactor = 8.0;
/// Most pixels measured per source: larger discs are read on a stride.
constexpr double kMaxMeasured = 1 << 20;
/// A (ring, direction) bin's quantile needs this many pixels.
constexpr size_t kMinBinPixels = 8;
/// The share of a pixel's light at and above which glare invalidates it *(choice)*: the
/// surface's own light is then at most half of what the pixel holds.
constexpr double kInvalidShare = 0.5;
/// A (ring, direction) bin whose 90% quantile is at least this share of the clip level is not
/// measured *(choice)*.
constexpr double kBrightBin = 0.9;
/// The share of the floor's excess (weighted sum of squares) a veil's fit may leave unexplained.
constexpr double kMaxUnexplained = 0.05;
/// Fits whose residual is within this factor of the best one explain the excess as well.
constexpr double kNearBest = 1.25;
/// A source whose veil at R_b is under this many noise levels has no flare.
constexpr double kMinVeilNoise = 1.0;

/// A source's measured veil, a Moffat profile G(d) = a·(1 + (d/α)²)^−β (d from the source's
/// centroid), out to `reach` pixels.
struct Veil {
  double cx = 0, cy = 0;
  double r0 = 0.0;  ///< the bloom reach R_b, where measuring starts
  double a = 0.0, alpha = 1.0, beta = 1.0, reach = 0.0;
  double At(double d) const { return a * std::pow(1.0 + (d / alpha) * (d / alpha), -beta); }
};

/// The least squares of three non-negative unknowns x (normal equations m·x = r, Σ w q² = sqq),
/// the last at most `cap`: every subset of free unknowns is solved (the others at 0, or the
/// last at its cap) and the feasible one of least residual kept. Returns x and its residual.
std::pair<Eigen::Vector3d, double> NonNegativeLeastSquares(const Eigen::Matrix3d& m,
                                                           const Eigen::Vector3d& r, double sqq,
                                                           double cap) {
  Eigen::Vector3d best_x = Eigen::Vector3d::Zero();
  double best_r = sqq;
  for (int mask = 1; mask < 16; ++mask) {  // bits 0-2: free unknowns; bit 3: the last at cap
    const bool capped = mask & 8;
    if (capped && ((mask & 4) || !std::isfinite(cap))) continue;
    Eigen::Vector3d x = Eigen::Vector3d::Zero();
    if (capped) x(2) = cap;
    std::vector<int> free;
    for (int i = 0; i < 3; ++i) {
      if (mask & (1 << i)) free.push_back(i);
    }
    if (!free.empty()) {
      const int n = int(free.size());
      Eigen::MatrixXd a(n, n);
      Eigen::VectorXd b(n);
      for (int i = 0; i < n; ++i) {
        b(i) = r(free[size_t(i)]) - m(free[size_t(i)], 2) * x(2);
        for (int j = 0; j < n; ++j) a(i, j) = m(free[size_t(i)], free[size_t(j)]);
      }
      Eigen::LDLT<Eigen::MatrixXd> ldlt(a);
      if (ldlt.info() != Eigen::Success || !(std::abs(a.determinant()) > 1e-12 * a.trace())) {
        continue;
      }
      const Eigen::VectorXd y = ldlt.solve(b);
      for (int i = 0; i < n; ++i) x(free[size_t(i)]) = y(i);
    }
    if (x.minCoeff() < 0.0 || x(2) > cap) continue;
    const double res = sqq - 2.0 * r.dot(x) + x.dot(m * x);
    if (res < best_r) best_r = res, best_x = x;
  }
  return {best_x, best_r};
}

/// Measures blob b's veil (a = 0: none).
Veil MeasureVeil(const geometry::LinearImage& image, const internal::ClippedBlobs& blobs,
                 size_t b, bool wrap) {
  const int W = image.width_px, H = image.height_px;
  Veil veil;
  veil.cx = blobs.centre_x[b];
  veil.cy = blobs.centre_y[b];
  veil.r0 = internal::BloomReachPx(blobs.area[b], H);
  const double outer = std::min(0.5 * H, kOuterFactor * veil.r0);
  if (!(outer > 2.0 * veil.r0)) return veil;
  const double log_span = std::log(outer / veil.r0);
  // Half-widths of the box read: a panorama's columns wrap, once at most.
  const int half_x = wrap ? std::min(int(std::ceil(outer)), W / 2) : int(std::ceil(outer));
  const int half_y = int(std::ceil(outer));
  const double disc = M_PI * outer * outer;
  const int stride = std::max(1, int(std::ceil(std::sqrt(disc / kMaxMeasured))));
  std::vector<std::vector<float>> bins(size_t(kRings) * kSectors);
  const int y_lo = std::max(0, int(std::floor(veil.cy)) - half_y);
  const int y_hi = std::min(H - 1, int(std::floor(veil.cy)) + half_y);
  for (int y = y_lo; y <= y_hi; y += stride) {
    for (int dx = -half_x; dx <= half_x; dx += stride) {
      int x = int(std::floor(veil.cx)) + dx;
      if (wrap) {
        x = ((x % W) + W) % W;
      } else if (x < 0 || x >= W) {
        continue;
      }
      const double ex = double(int(std::floor(veil.cx)) + dx) + 0.5 - veil.cx;
      const double ey = y + 0.5 - veil.cy;
      const double d = std::hypot(ex, ey);
      if (d < veil.r0 || d >= outer) continue;
      const size_t p = size_t(y) * W + size_t(x);
      if (blobs.clipped[p]) continue;
      const int ring = std::min(kRings - 1, int(kRings * std::log(d / veil.r0) / log_span));
      const double angle = std::atan2(ey, ex);
      const int s = int(std::floor((angle + M_PI) / (2.0 * M_PI) * kSectors)) % kSectors;
      bins[size_t(ring) * kSectors + size_t(s)].push_back(internal::Level(image, p));
    }
  }
  // Per direction: each ring's low quantile (a veil lifts a ring's darkest pixels as much as
  // its brightest; texture leaves them at its darkest level), and its fall to the next ring.
  std::vector<double> ring_d(kRings);
  for (int j = 0; j < kRings; ++j) {  // each ring's geometric middle
    ring_d[size_t(j)] = veil.r0 * std::exp(log_span * (j + 0.5) / kRings);
  }
  // Per ring, over the directions measured: the falls of the dark floor and of the contrast.
  std::vector<std::vector<double>> fall(kRings - 1), contrast_fall(kRings - 1);
  // Per ring, the darkest direction's floor: the veil is light every pixel there holds, so it
  // is at most that (however dark the scene's own surfaces are).
  std::vector<double> ceiling(kRings, std::numeric_limits<double>::infinity());
  for (int s = 0; s < kSectors; ++s) {
    std::vector<double> floor(kRings, -1.0), contrast(kRings, 0.0);
    for (int j = 0; j < kRings; ++j) {
      std::vector<float>& v = bins[size_t(j) * kSectors + size_t(s)];
      if (v.size() < kMinBinPixels) continue;
      auto low = v.begin() + ptrdiff_t(kRingQuantile * double(v.size() - 1));
      std::nth_element(v.begin(), low, v.end());
      floor[size_t(j)] = double(*low);
      ceiling[size_t(j)] = std::min(ceiling[size_t(j)], floor[size_t(j)]);
      auto high = v.begin() + ptrdiff_t((1.0 - kRingQuantile) * double(v.size() - 1));
      std::nth_element(low + 1, high, v.end());
      // A bin whose bright pixels near the clip level has its contrast cut by the clip: a
      // bright region round the source, where a veil cannot be told from a lit scene.
      if (double(*high) >= kBrightBin) {
        floor[size_t(j)] = -1.0;
        continue;
      }
      contrast[size_t(j)] = double(*high) - floor[size_t(j)];
    }
    // The direction's falls from ring to ring, each the median of the falls within two rings
    // of it: a veil falls smoothly, while an edge of the scene (a band of texture, a wall, the
    // sky) falls or rises at one ring or two.
    std::vector<double> d_floor(kRings - 1, std::nan("")), d_contrast(kRings - 1, std::nan(""));
    for (int j = 0; j + 1 < kRings; ++j) {
      if (floor[size_t(j)] >= 0.0 && floor[size_t(j + 1)] >= 0.0) {
        d_floor[size_t(j)] = floor[size_t(j)] - floor[size_t(j + 1)];
        d_contrast[size_t(j)] = contrast[size_t(j)] - contrast[size_t(j + 1)];
      }
    }
    auto smoothed = [](const std::vector<double>& d, int j) {
      std::vector<double> window;
      for (int i = std::max(0, j - 2); i <= std::min(int(d.size()) - 1, j + 2); ++i) {
        if (!std::isnan(d[size_t(i)])) window.push_back(d[size_t(i)]);
      }
      std::nth_element(window.begin(), window.begin() + window.size() / 2, window.end());
      return window[window.size() / 2];
    };
    for (int j = 0; j + 1 < kRings; ++j) {
      if (std::isnan(d_floor[size_t(j)])) continue;
      fall[size_t(j)].push_back(smoothed(d_floor, j));
      contrast_fall[size_t(j)].push_back(smoothed(d_contrast, j));
    }
  }
  // The consensus: per ring, the median of the directions' falls (a veil falls smoothly alike
  // in every direction; an edge of the scene, a band of texture, a wall or the sky falls or
  // rises at one ring in a few directions), summed from the outermost ring inward: the floor's
  // and the contrast's excess over their levels at the outermost ring.
  std::vector<double> d_used, q_used, c_used;
  double excess = 0.0, contrast_excess = 0.0;
  for (int j = kRings - 2; j >= 0; --j) {
    std::vector<double>& e = fall[size_t(j)];
    std::vector<double>& c = contrast_fall[size_t(j)];
    if (int(e.size()) < kSectors / 2) break;
    std::nth_element(e.begin(), e.begin() + e.size() / 2, e.end());
    std::nth_element(c.begin(), c.begin() + c.size() / 2, c.end());
    excess += e[e.size() / 2];
    contrast_excess += c[c.size() / 2];
    d_used.push_back(ring_d[size_t(j)]);
    q_used.push_back(excess);
    c_used.push_back(contrast_excess);
  }
  if (int(d_used.size()) < kRings / 2) return veil;
  // A source in a bright region (a window, the sky, a lit white wall) is not a point of light
  // whose veil the profile measures: its surround must be measured in most directions.
  if (4 * fall[0].size() < 3 * kSectors) return veil;
  // A veil lifts the dark floor without lifting the texture's contrast; a surface lit more
  // brightly toward the source (a wall beside a window, a ceiling round a lamp) lifts both in
  // proportion, and the scene may brighten slowly toward the source whatever it holds. So the
  // floor's excess is fitted as k·(contrast excess) + s·ln(d_far/d) + a·(f(d) − f(d_far)),
  // k, s, a ≥ 0 and f a Moffat profile, by weighted least squares (relative errors: the faint
  // tail over dark surfaces matters as much as the core), for the (α, β) of a grid.
  const double d_far = ring_d[kRings - 1];
  struct Fit {
    double residual, alpha, beta, a;
  };
  std::vector<Fit> fits;
  double best = std::numeric_limits<double>::infinity(), sqq_all = 0.0;
  for (int ia = -8; ia <= 16; ++ia) {  // α from R_b/16 to 4·R_b
    for (double beta = 1.0; beta <= 3.0 + 1e-9; beta += 0.0625) {
      const double alpha = veil.r0 * std::pow(2.0, -0.25 * ia);
      auto f = [&](double d) { return std::pow(1.0 + (d / alpha) * (d / alpha), -beta); };
      Eigen::Matrix3d m = Eigen::Matrix3d::Zero();  // normal equations over (k, s, a)
      Eigen::Vector3d r = Eigen::Vector3d::Zero();
      double sqq = 0.0;
      for (size_t i = 0; i < d_used.size(); ++i) {
        const Eigen::Vector3d x(c_used[i], std::log(d_far / d_used[i]), f(d_used[i]) - f(d_far));
        const double w = 1.0 / ((q_used[i] + 0.5 * kNoise) * (q_used[i] + 0.5 * kNoise));
        m += w * x * x.transpose();
        r += w * q_used[i] * x;
        sqq += w * q_used[i] * q_used[i];
      }
      // The veil under every ring's ceiling: its amplitude is at most `cap`.
      double cap = std::numeric_limits<double>::infinity();
      for (int j = 0; j < kRings; ++j) {
        if (std::isfinite(ceiling[size_t(j)])) {
          cap = std::min(cap, ceiling[size_t(j)] / f(ring_d[size_t(j)]));
        }
      }
      const auto [best_x, best_r] = NonNegativeLeastSquares(m, r, sqq, cap);
      fits.push_back({best_r, alpha, beta, best_x(2)});
      best = std::min(best, best_r);
      sqq_all = sqq;
    }
  }
  // Over the rings measured, fits of several (α, β) explain the excess about as well; of
  // those within a quarter of the best residual, the slowest fall (the lowest β) is kept: the
  // tail beyond the rings measured follows the CIE law's 1/θ² rather than a guess steeper.
  double kept_beta = std::numeric_limits<double>::infinity(), kept_residual = best;
  for (const Fit& fit : fits) {
    if (fit.residual > kNearBest * best + 1e-12 * sqq_all) continue;
    if (fit.beta < kept_beta || (fit.beta == kept_beta && fit.residual < kept_residual)) {
      kept_beta = fit.beta, kept_residual = fit.residual;
      veil.a = fit.a, veil.alpha = fit.alpha, veil.beta = fit.beta;
    }
  }
  // A profile the model does not explain is the scene's, not a veil.
  if (!(veil.At(veil.r0) > kMinVeilNoise * kNoise) || best > kMaxUnexplained * sqq_all) {
    veil.a = 0.0;
    return veil;
  }
  // Out to where the veil falls under half the noise, within the image height.
  veil.reach = veil.r0;
  while (veil.reach < H && veil.At(veil.reach) >= 0.5 * kNoise) veil.reach *= 1.05;
  veil.reach = std::min(veil.reach, double(H));
  return veil;
}

}  // namespace

double FlareMap::CoveredFraction(int width_px, int height_px) const {
  const double pixels = double(width_px) * double(height_px);
  return pixels > 0.0 ? double(invalid_pixels + soft_pixels) / pixels : 0.0;
}

FlareMap DetectFlare(const geometry::LinearImage& image, bool wrap) {
  return DetectFlare(image, internal::FindClippedBlobs(image, wrap), wrap);
}

FlareMap DetectFlare(const geometry::LinearImage& image, const internal::ClippedBlobs& blobs,
                     bool wrap) {
  FlareMap out;
  if (blobs.size() == 0) return out;
  const int W = image.width_px, H = image.height_px;
  std::vector<size_t> by_area(blobs.size());
  std::iota(by_area.begin(), by_area.end(), size_t{0});
  std::stable_sort(by_area.begin(), by_area.end(),
                   [&](size_t a, size_t b) { return blobs.area[a] > blobs.area[b]; });
  by_area.resize(std::min(by_area.size(), kMaxFlareSources));
  std::vector<Veil> measured(by_area.size());
  tbb::parallel_for(size_t{0}, by_area.size(), [&](size_t i) {
    measured[i] = MeasureVeil(image, blobs, by_area[i], wrap);
  });
  // Larger sources first; a blob within a kept source's bloom reach is a fragment of it (a lamp
  // split by its fitting), whose veil the source's already holds.
  std::vector<Veil> veils;
  for (const Veil& v : measured) {
    if (!(v.a > 0.0)) continue;
    bool fragment = false;
    for (const Veil& kept : veils) {
      double dx = std::abs(v.cx - kept.cx);
      if (wrap) dx = std::min(dx, W - dx);
      fragment |= std::hypot(dx, v.cy - kept.cy) < kept.r0;
    }
    if (!fragment) veils.push_back(v);
  }
  out.sources = int(veils.size());
  if (veils.empty()) return out;

  // The glare per pixel, and the distance to the nearest veiled source.
  out.conf = internal::ConfidenceOnes(W, H);
  struct Count {
    int64_t invalid = 0, soft = 0;
    double radius = 0.0;
  };
  tbb::enumerable_thread_specific<Count> counts;
  tbb::parallel_for(tbb::blocked_range<int>(0, H), [&](const tbb::blocked_range<int>& rows) {
    Count& count = counts.local();
    std::vector<double> glare(static_cast<size_t>(W));
    std::vector<float> nearest(static_cast<size_t>(W));
    for (int y = rows.begin(); y != rows.end(); ++y) {
      std::fill(glare.begin(), glare.end(), 0.0);
      std::fill(nearest.begin(), nearest.end(), std::numeric_limits<float>::infinity());
      for (const Veil& v : veils) {
        const double ey = y + 0.5 - v.cy;
        if (std::abs(ey) >= v.reach) continue;
        const double half = std::sqrt(v.reach * v.reach - ey * ey);
        const int span = wrap ? std::min(int(std::ceil(half)), W / 2) : int(std::ceil(half));
        const int cx = int(std::floor(v.cx));
        for (int dx = -span; dx <= span; ++dx) {
          int x = cx + dx;
          if (wrap) {
            x = ((x % W) + W) % W;
          } else if (x < 0 || x >= W) {
            continue;
          }
          const double d = std::hypot(double(cx + dx) + 0.5 - v.cx, ey);
          if (d >= v.reach) continue;
          glare[size_t(x)] += v.At(std::max(d, 0.5 * v.r0));
          nearest[size_t(x)] = std::min(nearest[size_t(x)], float(d));
        }
      }
      for (int x = 0; x < W; ++x) {
        const size_t p = size_t(y) * W + size_t(x);
        if (!(glare[size_t(x)] > 0.0) || blobs.clipped[p]) continue;
        const double share = glare[size_t(x)] / std::max(double(internal::Level(image, p)), 1e-6);
        if (1.0 - share >= 1.0 / (1.0 + kAffectedShare)) continue;
        if (share >= kInvalidShare) {
          out.conf.pixels[p] = 0.0f;
          ++count.invalid;
        } else {
          out.conf.pixels[p] = float(1.0 - share);
          ++count.soft;
        }
        count.radius = std::max(count.radius, double(nearest[size_t(x)]));
      }
    }
  });
  for (const Count& c : counts) {
    out.invalid_pixels += c.invalid;
    out.soft_pixels += c.soft;
    out.max_radius_px = std::max(out.max_radius_px, int(std::ceil(c.radius)));
  }
  return out;
}

}  // namespace vasl::ingest

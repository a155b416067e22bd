/// @file smear.cc
/// @brief Readout smear (VASL-MODEL §9): columns lifted uniformly through clipped sources.
#include <algorithm>
#include <cmath>
#include <vector>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include "lattice/ingest/artefacts.h"
#include "lattice/ingest/artefacts_internal.h"

namespace vasl::ingest {

using internal::ClippedBlobs;
using internal::kAffectedShare;
using internal::kNoise;
using internal::Level;

namespace {

/// The interquartile mean of `v` (the mean of its middle half: texture that lifts rows as often
/// up as down leaves it at 0, even when it takes two values only) and four standard errors of
/// it (σ from the interquartile range); sorts v.
std::pair<double, double> CentreAndBound(std::vector<float>& v) {
  std::sort(v.begin(), v.end());
  const size_t q1 = v.size() / 4, q3 = v.size() - v.size() / 4;
  double sum = 0.0;
  for (size_t i = q1; i < q3; ++i) sum += v[i];
  const double centre = sum / double(q3 - q1);
  const double sigma = (v[q3 - 1] - v[q1]) / 1.349;
  return {centre, 4.0 * sigma / std::sqrt(double(q3 - q1))};
}

}  // namespace

double SmearMap::CoveredFraction(int width_px, int height_px) const {
  return width_px > 0 && height_px > 0 ? double(soft_pixels) / (double(width_px) * height_px)
                                       : 0.0;
}

SmearMap DetectSmear(const geometry::LinearImage& image, bool wrap) {
  return DetectSmear(image, internal::FindClippedBlobs(image, wrap), wrap);
}

SmearMap DetectSmear(const geometry::LinearImage& image, const ClippedBlobs& blobs, bool wrap) {
  SmearMap out;
  const int W = image.width_px, H = image.height_px;
  if (blobs.size() == 0 || W <= 0 || H <= 0) return out;
  // Per column, the rows its blobs and their bloom reach take, top to bottom (none: top > bottom).
  std::vector<int> top(size_t(W), H), bottom(size_t(W), -1);
  for (size_t b = 0; b < blobs.size(); ++b) {
    if (blobs.box_x1[b] - blobs.box_x0[b] + 1 > W / 8) continue;  // a blob across the seam, or huge
    const int reach = internal::BloomReachPx(blobs.area[b], H);
    for (int x = blobs.box_x0[b]; x <= blobs.box_x1[b]; ++x) {
      top[size_t(x)] = std::min(top[size_t(x)], blobs.box_y0[b] - reach);
      bottom[size_t(x)] = std::max(bottom[size_t(x)], blobs.box_y1[b] + reach);
    }
  }
  std::vector<uint8_t> covered(size_t(W), 0);
  for (int x = 0; x < W; ++x) covered[size_t(x)] = bottom[size_t(x)] >= 0;
  // The nearest column on side `step` (−1, +1) that no blob covers, two pixels further out.
  auto free_column = [&](int x, int step) {
    int c = x;
    for (int i = 0; i < W; ++i) {
      c += step;
      if (wrap) c = (c + W) % W;
      if (c < 0 || c >= W) return -1;
      if (!covered[size_t(c)]) break;
    }
    c += 2 * step;
    if (wrap) c = (c + W) % W;
    return c >= 0 && c < W && !covered[size_t(c)] ? c : -1;
  };
  std::vector<float> smear(size_t(W), 0.0f);
  tbb::parallel_for(tbb::blocked_range<int>(0, W, 8), [&](const tbb::blocked_range<int>& r) {
    std::vector<float> above, below;
    for (int x = r.begin(); x != r.end(); ++x) {
      if (!covered[size_t(x)]) continue;
      const int xl = free_column(x, -1), xr = free_column(x, +1);
      if (xl < 0 && xr < 0) continue;
      above.clear();
      below.clear();
      for (int y = 0; y < H; ++y) {
        if (y >= top[size_t(x)] && y <= bottom[size_t(x)]) continue;
        const size_t row = size_t(y) * W;
        if (!blobs.clipped.empty() && blobs.clipped[row + x]) continue;
        double side = 0.0;
        int n = 0;
        for (int c : {xl, xr}) {
          if (c < 0 || (!blobs.clipped.empty() && blobs.clipped[row + c])) continue;
          side += Level(image, row + c);
          ++n;
        }
        if (n == 0) continue;
        (y < top[size_t(x)] ? above : below).push_back(float(Level(image, row + x) - side / n));
      }
      const size_t min_rows = size_t(std::max(16, H / 16));
      double s = -1.0;
      for (std::vector<float>* v : {&above, &below}) {
        if (v->size() < min_rows) continue;
        const auto [centre, bound] = CentreAndBound(*v);
        if (!(centre > kNoise && centre > bound)) {
          s = -1.0;
          break;
        }
        if (s < 0.0) {
          s = centre;
        } else if (std::max(s, centre) > 2.0 * std::min(s, centre)) {
          s = -1.0;  // lifted unevenly: scene, not smear
          break;
        } else {
          s = std::min(s, centre);
        }
      }
      if (s > 0.0 && above.size() + below.size() >= size_t(H / 4)) smear[size_t(x)] = float(s);
    }
  });
  for (int x = 0; x < W; ++x) {
    if (!(smear[size_t(x)] > 0.0f)) continue;
    if (out.column_offset.empty()) out.column_offset.assign(size_t(W), 0.0f);
    out.column_offset[size_t(x)] = smear[size_t(x)];
    if (out.conf.pixels.empty()) out.conf = internal::ConfidenceOnes(W, H);
    ++out.columns;
    out.max_offset = std::max(out.max_offset, double(smear[size_t(x)]));
    for (int y = 0; y < H; ++y) {
      const size_t p = size_t(y) * W + x;
      if (!blobs.clipped.empty() && blobs.clipped[p]) continue;  // saturation's 0 already
      const float level = Level(image, p);
      if (smear[size_t(x)] > kAffectedShare * level) {
        out.conf.pixels[p] = std::max(0.0f, 1.0f - smear[size_t(x)] / std::max(level, 1e-6f));
        ++out.soft_pixels;
      }
    }
  }
  return out;
}

}  // namespace vasl::ingest

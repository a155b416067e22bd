/// @file saturation.cc
/// @brief Saturation and blooming as per-pixel confidence (VASL-MODEL §9).
#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

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

/// Most (ring, direction) bins measured per image: blobs beyond them, the smallest, get no halo.
constexpr size_t kMaxBins = size_t{16} << 20;
/// Rings over which a profile that falls by less than kNoise has met the surround.
constexpr int kFlatRings = 3;
/// A ring's quantile, in one direction, needs this many pixels.
constexpr size_t kMinRingPixels = 3;

/// Felzenszwalb–Huttenlocher 1D squared distance transform of f over n samples: d[q] =
/// min_p (q − p)² + f[p], and arg[q] the p that attains it.
void DistanceTransform1d(const double* f, int n, double* d, int* arg, int* v, double* z) {
  const double inf = std::numeric_limits<double>::infinity();
  int k = 0;
  v[0] = 0;
  z[0] = -inf;
  z[1] = inf;
  auto meet = [&](int q, int p) {  // where the parabolas of q and p cross
    return ((f[q] + double(q) * q) - (f[p] + double(p) * p)) / (2.0 * q - 2.0 * p);
  };
  for (int q = 1; q < n; ++q) {
    double s = meet(q, v[k]);
    while (s <= z[k]) s = meet(q, v[--k]);  // z[0] = −∞ stops it
    ++k;
    v[k] = q;
    z[k] = s;
    z[k + 1] = inf;
  }
  k = 0;
  for (int q = 0; q < n; ++q) {
    while (z[k + 1] < q) ++k;
    d[q] = (double(q) - v[k]) * (double(q) - v[k]) + f[v[k]];
    arg[q] = v[k];
  }
}

}  // namespace

double SaturationMap::CoveredFraction(int width_px, int height_px) const {
  const double pixels = double(width_px) * double(height_px);
  return pixels > 0.0 ? double(clipped_pixels + halo_pixels) / pixels : 0.0;
}

SaturationMap DetectSaturation(const geometry::LinearImage& image, bool wrap) {
  return DetectSaturation(image, internal::FindClippedBlobs(image, wrap));
}

SaturationMap DetectSaturation(const geometry::LinearImage& image,
                               const internal::ClippedBlobs& blobs) {
  SaturationMap out;
  out.clipped_pixels = blobs.clipped_pixels;
  if (blobs.clipped_pixels == 0) return out;
  const int W = image.width_px, H = image.height_px;
  const size_t n = size_t(W) * size_t(H);
  auto level = [&](size_t p) { return internal::Level(image, p); };
  const std::vector<uint8_t>& clipped = blobs.clipped;
  const std::vector<int32_t>& label = blobs.label;
  const std::vector<int64_t>& area = blobs.area;
  const std::vector<int>& box_x0 = blobs.box_x0;
  const std::vector<int>& box_x1 = blobs.box_x1;
  const std::vector<int>& box_y0 = blobs.box_y0;
  const std::vector<int>& box_y1 = blobs.box_y1;
  out.blobs = int(area.size());
  // R_b, pixels; the largest blobs first while their rings fit kMaxBins (an image speckled
  // with millions of clipped specks keeps its specks at 0, without halos, in bounded memory).
  std::vector<int> reach(area.size(), 0);
  std::vector<size_t> by_area(area.size());
  for (size_t b = 0; b < by_area.size(); ++b) by_area[b] = b;
  std::stable_sort(by_area.begin(), by_area.end(),
                   [&](size_t a, size_t b) { return area[a] > area[b]; });
  size_t bins = 0;
  int x0 = W, x1 = -1, y0 = H, y1 = -1;  // the region every blob's rings lie in
  for (size_t b : by_area) {
    const int R = internal::BloomReachPx(area[b], H);
    if (bins + size_t(R) * kSectors > kMaxBins) break;
    bins += size_t(R) * kSectors;
    reach[b] = R;
    x0 = std::min(x0, box_x0[b] - R), x1 = std::max(x1, box_x1[b] + R);
    y0 = std::min(y0, box_y0[b] - R), y1 = std::max(y1, box_y1[b] + R);
  }
  x0 = std::max(0, x0), x1 = std::min(W - 1, x1), y0 = std::max(0, y0), y1 = std::min(H - 1, y1);
  const int bw = std::max(0, x1 - x0 + 1), bh = std::max(0, y1 - y0 + 1);

  // Exact Euclidean distance to the nearest clipped pixel over that region: columns, then rows.
  const double far = 1e20;
  std::vector<double> col_d2(size_t(bw) * bh);
  std::vector<int> col_arg(size_t(bw) * bh);  // nearest clipped row in the column
  tbb::parallel_for(tbb::blocked_range<int>(0, bw), [&](const tbb::blocked_range<int>& cols) {
    std::vector<double> f(bh), d(bh), z(bh + 1);
    std::vector<int> arg(bh), v(bh);
    for (int i = cols.begin(); i != cols.end(); ++i) {
      for (int j = 0; j < bh; ++j) f[j] = clipped[size_t(y0 + j) * W + x0 + i] ? 0.0 : far;
      DistanceTransform1d(f.data(), bh, d.data(), arg.data(), v.data(), z.data());
      for (int j = 0; j < bh; ++j) {
        col_d2[size_t(j) * bw + i] = d[j];
        col_arg[size_t(j) * bw + i] = arg[j];
      }
    }
  });
  std::vector<float> dist(size_t(bw) * bh);
  std::vector<int32_t> nearest(size_t(bw) * bh);  // the blob of the nearest clipped pixel
  std::vector<uint8_t> sector(size_t(bw) * bh);   // the direction from it, of kSectors
  tbb::parallel_for(tbb::blocked_range<int>(0, bh), [&](const tbb::blocked_range<int>& rows) {
    std::vector<double> d(bw), z(bw + 1);
    std::vector<int> arg(bw), v(bw);
    for (int j = rows.begin(); j != rows.end(); ++j) {
      const double* f = &col_d2[size_t(j) * bw];
      DistanceTransform1d(f, bw, d.data(), arg.data(), v.data(), z.data());
      for (int i = 0; i < bw; ++i) {
        const size_t o = size_t(j) * bw + i;
        const bool found = d[i] < 0.5 * far;
        dist[o] = found ? float(std::sqrt(d[i])) : std::numeric_limits<float>::infinity();
        const int sx = x0 + arg[i], sy = y0 + col_arg[size_t(j) * bw + arg[i]];
        nearest[o] = found ? label[size_t(sy) * W + sx] : -1;
        if (found && dist[o] < float(reach[size_t(nearest[o])])) {  // on one of its rings
          const double angle = std::atan2(double(y0 + j - sy), double(x0 + i - sx));  // [−π, π]
          sector[o] = uint8_t(int(std::floor((angle + M_PI) / (2.0 * M_PI) * kSectors)) % kSectors);
        }
      }
    }
  });

  // Each blob's rings: the pixels at ⌊distance⌋ = k from it, k = 1 .. R_b − 1.
  std::vector<size_t> ring_begin(area.size() + 1, 0);
  for (size_t b = 0; b < area.size(); ++b) ring_begin[b + 1] = ring_begin[b] + size_t(reach[b]);
  std::vector<uint32_t> bin_count(ring_begin.back() * kSectors + 1, 0);
  auto ring_of = [&](size_t o) -> int64_t {  // index into the rings, or −1
    const int32_t b = nearest[o];
    if (b < 0 || !(dist[o] >= 1.0f)) return -1;  // no blob, or clipped itself
    const int k = int(dist[o]);
    return k < reach[size_t(b)] ? int64_t(ring_begin[size_t(b)] + size_t(k)) : -1;
  };
  auto bin_of = [&](size_t o) -> int64_t {  // index into the (ring, sector) bins, or −1
    const int64_t r = ring_of(o);
    return r < 0 ? -1 : r * kSectors + sector[o];
  };
  for (size_t o = 0; o < dist.size(); ++o) {
    if (const int64_t r = bin_of(o); r >= 0) ++bin_count[size_t(r)];
  }
  std::vector<size_t> value_begin(bin_count.size() + 1, 0);
  for (size_t r = 0; r < bin_count.size(); ++r) value_begin[r + 1] = value_begin[r] + bin_count[r];
  std::vector<float> values(value_begin.back());
  std::vector<size_t> fill(value_begin.begin(), value_begin.end() - 1);
  for (int j = 0; j < bh; ++j) {
    for (int i = 0; i < bw; ++i) {
      const size_t o = size_t(j) * bw + i;
      if (const int64_t r = bin_of(o); r >= 0) {
        values[fill[size_t(r)]++] = level(size_t(y0 + j) * W + x0 + i);
      }
    }
  }
  // Per blob and direction: each ring's low quantile, made non-increasing outward, falls to
  // the surround's own level in that direction; its excess there is that direction's bloom.
  // Bloom spreads alike in every direction and scene content does not, so a ring's bloom Δ_k
  // is the median over the directions.
  std::vector<float> ring_bloom(ring_begin.back(), 0.0f);
  tbb::parallel_for(size_t{0}, area.size(), [&](size_t b) {
    const int R = reach[b];
    std::vector<std::vector<double>> excess(kSectors, std::vector<double>(size_t(R), -1.0));
    for (int s = 0; s < kSectors; ++s) {
      std::vector<double> profile(size_t(R), -1.0);  // −1: too few pixels
      double running = std::numeric_limits<double>::infinity();
      for (int k = 1; k < R; ++k) {
        const size_t r = (ring_begin[b] + size_t(k)) * kSectors + size_t(s);
        float* first = values.data() + value_begin[r];
        float* last = values.data() + value_begin[r + 1];
        if (size_t(last - first) < kMinRingPixels) continue;
        float* at = first + ptrdiff_t(kRingQuantile * double(last - first - 1));
        std::nth_element(first, at, last);
        running = std::min(running, double(*at));
        profile[size_t(k)] = running;
      }
      if (!std::isfinite(running)) continue;
      int k0 = 1;
      while (profile[size_t(k0)] < 0.0) ++k0;
      for (int k = k0 + 1; k < R; ++k) {  // a bin too thin to measure reads as the one inside
        if (profile[size_t(k)] < 0.0) profile[size_t(k)] = profile[size_t(k - 1)];
      }
      // What the scene itself does there: its slope g per ring, the median fall of the outer
      // half of the rings (a surface lit more brightly toward a lamp falls slowly and evenly;
      // bloom falls fast and ever more slowly).
      std::vector<double> fall;
      for (int k = std::max(k0, R / 2); k + 1 < R; ++k) {
        fall.push_back(profile[size_t(k)] - profile[size_t(k + 1)]);
      }
      double g = 0.0;
      if (!fall.empty()) {
        std::nth_element(fall.begin(), fall.begin() + fall.size() / 2, fall.end());
        g = fall[fall.size() / 2];
      }
      // The halo ends where the profile falls no faster than the scene (by less than half the
      // noise beyond g·kFlatRings over the next kFlatRings rings). The surround inside it is
      // the scene's level carried in along g from kFlatRings further out, where the tail has
      // faded. A profile that falls like the scene from its first ring (texture, a clipped
      // surface that does not bloom, a lit wall) has no halo.
      auto at = [&](int k) { return profile[size_t(std::min(k, R - 1))]; };
      int end = k0;
      while (end < R - 1 && at(end) - at(end + kFlatRings) - g * kFlatRings >= 0.5 * kNoise) ++end;
      const int far_ring = std::min(end + kFlatRings, R - 1);
      for (int k = k0; k < R; ++k) {
        const double surround = at(far_ring) + g * double(far_ring - k);
        excess[size_t(s)][size_t(k)] = k < end ? std::max(0.0, profile[size_t(k)] - surround) : 0.0;
      }
    }
    std::vector<double> at_k;
    for (int k = 1; k < R; ++k) {
      at_k.clear();
      for (int s = 0; s < kSectors; ++s) {
        if (excess[size_t(s)][size_t(k)] >= 0.0) at_k.push_back(excess[size_t(s)][size_t(k)]);
      }
      if (int(at_k.size()) < kSectors / 2) continue;  // a ring seen from too few directions
      std::nth_element(at_k.begin(), at_k.begin() + at_k.size() / 2, at_k.end());
      const double bloom = at_k[at_k.size() / 2];
      if (bloom > kNoise) ring_bloom[ring_begin[b] + size_t(k)] = float(bloom);
    }
  });

  out.conf = internal::ConfidenceOnes(W, H);
  tbb::parallel_for(tbb::blocked_range<size_t>(0, n, 1 << 16),
                    [&](const tbb::blocked_range<size_t>& r) {
                      for (size_t p = r.begin(); p != r.end(); ++p) {
                        out.conf.pixels[p] = clipped[p] ? 0.0f : 1.0f;
                      }
                    });
  // Per thread: halo pixels and each blob's widest halo.
  struct HaloCount {
    int64_t pixels = 0;
    std::vector<int> radius;
  };
  tbb::enumerable_thread_specific<HaloCount> counts([&] {
    return HaloCount{0, std::vector<int>(area.size(), 0)};
  });
  tbb::parallel_for(tbb::blocked_range<int>(0, bh), [&](const tbb::blocked_range<int>& rows) {
    HaloCount& count = counts.local();
    std::vector<int>& halo_radius = count.radius;
    for (int j = rows.begin(); j != rows.end(); ++j) {
      for (int i = 0; i < bw; ++i) {
        const size_t o = size_t(j) * bw + i;
        const int64_t r = ring_of(o);
        if (r < 0 || !(ring_bloom[size_t(r)] > 0.0f)) continue;
        // Bloom at the pixel's own distance: geometric between the centres of its ring and the
        // neighbouring one (bloom falls by a large factor across one ring), toward 0 past the
        // halo's last ring; the innermost ring keeps its own.
        const int k = int(dist[o]);
        const double t = double(dist[o]) - (k + 0.5);
        const size_t b = size_t(nearest[o]);
        const bool outward = t >= 0.0;
        const double here = ring_bloom[size_t(r)];
        double bloom = here;
        if (outward || k > 1) {
          const int kn = outward ? k + 1 : k - 1;
          const double next = kn < reach[b] ? double(ring_bloom[ring_begin[b] + size_t(kn)]) : 0.0;
          bloom = next > 0.0 ? here * std::pow(next / here, std::abs(t))
                             : here * (1.0 - std::abs(t));
        }
        // The share of the pixel's light that is its surface's: 1 − Δ / L(p).
        const size_t p = size_t(y0 + j) * W + x0 + i;
        const double own = 1.0 - bloom / std::max(double(level(p)), 1e-6);
        if (own >= 1.0 / (1.0 + kAffectedShare)) continue;
        out.conf.pixels[p] = float(std::max(0.0, own));
        ++count.pixels;
        halo_radius[b] = std::max(halo_radius[b], int(dist[o]) + 1);
      }
    }
  });
  for (const HaloCount& count : counts) {
    out.halo_pixels += count.pixels;
    for (int r : count.radius) out.max_halo_radius_px = std::max(out.max_halo_radius_px, r);
  }
  return out;
}

}  // namespace vasl::ingest

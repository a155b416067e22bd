/// @file fringing.cc
/// @brief Chromatic fringing (VASL-MODEL §9): per-channel offsets of the edges' centroids
///        against green's, measured at high-contrast edges, and the correction that resamples
///        each channel by its offset.
#include <algorithm>
#include <cmath>
#include <utility>
#include <vector>

#include <tbb/blocked_range.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>

#include "lattice/ingest/artefacts.h"
#include "lattice/ingest/artefacts_internal.h"

namespace vasl::ingest {
namespace {

using internal::kAffectedShare;

/// An edge is measured where green's central difference is at least this share of the clip
/// level *(choice)*: a high-contrast edge, whose centroid noise does not reach.
constexpr float kEdgeContrast = 0.08f;
/// A channel's edge counts where its own difference, within the window, has green's sign and
/// at least this share of green's (an edge in every channel, not a colour edge that one
/// channel does not share).
constexpr float kChannelShare = 0.25f;
/// Pixels either side of an edge over which each channel's gradient centroid is taken.
constexpr int kHalfWindow = 3;
/// Edge samples an axis needs, image-wide and per tile, before its median is trusted.
constexpr size_t kMinSamples = 200;
constexpr size_t kMinTileSamples = 100;
/// Offsets under this (pixels) are no fringing *(choice)*: a shift that small moves colour by
/// little, and leaving it uncorrected keeps clean images (and colour bloom) untouched.
constexpr double kMinOffsetPx = 0.2;
/// Tiles of the offset field: fringing grows toward a lens's rim, so it varies over the image.
constexpr int kTilesX = 8, kTilesY = 4;

/// One edge sample: its tile, and each of red's and blue's offset against green's.
struct Sample {
  int tile;
  float offset[2];  // red, blue
};

/// Catmull-Rom weights of the four samples around a point at fraction t past the second: a
/// cubic that keeps an edge sharper than bilinear resampling does.
void CatmullRom(float t, float* w) {
  const float t2 = t * t, t3 = t2 * t;
  w[0] = 0.5f * (-t3 + 2.0f * t2 - t);
  w[1] = 0.5f * (3.0f * t3 - 5.0f * t2 + 2.0f);
  w[2] = 0.5f * (-3.0f * t3 + 4.0f * t2 + t);
  w[3] = 0.5f * (t3 - t2);
}

double Median(std::vector<float>& v) {
  if (v.empty()) return 0.0;
  std::nth_element(v.begin(), v.begin() + ptrdiff_t(v.size() / 2), v.end());
  return v[v.size() / 2];
}

}  // namespace

std::pair<double, double> ChannelShift::Offset(int channel, double x, double y) const {
  if (!found || channel == 1) return {0.0, 0.0};
  const int c = channel == 0 ? 0 : 1;
  // Bilinear between tile centres; columns wrap on a panorama, rows clamp.
  const double tx = x / width_px * tiles_x - 0.5, ty = y / height_px * tiles_y - 0.5;
  const int x0 = int(std::floor(tx)), y0 = int(std::floor(ty));
  const double fx = tx - x0, fy = ty - y0;
  auto at = [&](int i, int j, const std::vector<float>& field) {
    if (!wrap) {
      i = std::clamp(i, 0, tiles_x - 1);
    } else if (i < 0 || i >= tiles_x) {
      i = ((i % tiles_x) + tiles_x) % tiles_x;
    }
    j = std::clamp(j, 0, tiles_y - 1);
    return double(field[(size_t(j) * tiles_x + size_t(i)) * 2 + size_t(c)]);
  };
  auto lerp = [&](const std::vector<float>& field) {
    return (1 - fy) * ((1 - fx) * at(x0, y0, field) + fx * at(x0 + 1, y0, field)) +
           fy * ((1 - fx) * at(x0, y0 + 1, field) + fx * at(x0 + 1, y0 + 1, field));
  };
  return {lerp(tile_dx), lerp(tile_dy)};
}

ChannelShift EstimateChannelShift(const geometry::LinearImage& image, bool wrap) {
  ChannelShift out;
  const int W = image.width_px, H = image.height_px, C = image.channels;
  out.width_px = W;
  out.height_px = H;
  out.wrap = wrap;
  if (C < 3 || W < 4 * kHalfWindow || H < 4 * kHalfWindow || !(image.clip_value > 0.0f) ||
      image.pixels.size() != size_t(W) * size_t(H) * size_t(C)) {
    return out;
  }
  const float inv_clip = 1.0f / image.clip_value;
  auto value = [&](int x, int y, int c) {
    if (wrap) x = ((x % W) + W) % W;
    x = std::clamp(x, 0, W - 1);
    y = std::clamp(y, 0, H - 1);
    return image.pixels[(size_t(y) * W + size_t(x)) * C + size_t(c)] * inv_clip;
  };
  // Central differences along an axis at (x, y): axis 0 along x, 1 along y.
  auto diff = [&](int x, int y, int c, int axis) {
    return axis == 0 ? value(x + 1, y, c) - value(x - 1, y, c)
                     : value(x, y + 1, c) - value(x, y - 1, c);
  };
  // Per axis, the edge samples: a pixel where green's difference along the axis is strong,
  // dominant over the other axis and a local maximum along it, and red's and blue's share it.
  tbb::enumerable_thread_specific<std::vector<Sample>> local[2];
  tbb::parallel_for(tbb::blocked_range<int>(1, H - 1), [&](const tbb::blocked_range<int>& rows) {
    std::vector<Sample>* samples[2] = {&local[0].local(), &local[1].local()};
    for (int y = rows.begin(); y != rows.end(); ++y) {
      // Green of rows y − 1, y and y + 1 (1 ≤ y ≤ H − 2): away from the columns that wrap,
      // the differences below are read straight from them, the same products and difference
      // as `diff`, and a pixel where neither reaches an edge's contrast (most of them) is
      // passed by without the wrap and clamps.
      const float* up = &image.pixels[size_t(y - 1) * W * C + 1];
      const float* row = up + size_t(W) * C;
      const float* down = row + size_t(W) * C;
      for (int x = wrap ? 0 : 1; x < (wrap ? W : W - 1); ++x) {
        if (x >= 1 && x + 1 < W) {
          const size_t at = size_t(x) * C;
          const float fx = row[at + C] * inv_clip - row[at - C] * inv_clip;
          const float fy = down[at] * inv_clip - up[at] * inv_clip;
          if (std::abs(fx) < kEdgeContrast && std::abs(fy) < kEdgeContrast) continue;
        }
        const float gx = diff(x, y, 1, 0), gy = diff(x, y, 1, 1);
        for (int axis = 0; axis < 2; ++axis) {
          const float g = axis == 0 ? gx : gy, other = axis == 0 ? gy : gx;
          if (std::abs(g) < kEdgeContrast || std::abs(g) < 2.0f * std::abs(other)) continue;
          const int sx = axis == 0 ? 1 : 0, sy = 1 - sx;
          if (std::abs(diff(x - sx, y - sy, 1, axis)) > std::abs(g) ||
              std::abs(diff(x + sx, y + sy, 1, axis)) > std::abs(g)) {
            continue;
          }
          if (axis == 1 && (y - kHalfWindow < 1 || y + kHalfWindow >= H - 1)) continue;
          if (axis == 0 && !wrap && (x - kHalfWindow < 1 || x + kHalfWindow >= W - 1)) continue;
          // Each channel's centroid of its gradient along the axis, where it has green's sign.
          const float sign = g > 0.0f ? 1.0f : -1.0f;
          double centroid[3];
          bool ok = true;
          for (int c = 0; c < 3 && ok; ++c) {
            double sum = 0.0, moment = 0.0, peak = 0.0;
            for (int t = -kHalfWindow; t <= kHalfWindow; ++t) {
              const double w = std::max(0.0f, sign * diff(x + t * sx, y + t * sy, c, axis));
              sum += w;
              moment += w * t;
              peak = std::max(peak, w);
            }
            ok = sum > 0.0 && peak >= kChannelShare * std::abs(g);
            centroid[c] = ok ? moment / sum : 0.0;
          }
          if (!ok) continue;
          const int tile = std::min(kTilesY - 1, y * kTilesY / H) * kTilesX +
                           std::min(kTilesX - 1, x * kTilesX / W);
          samples[axis]->push_back(
              {tile, {float(centroid[0] - centroid[1]), float(centroid[2] - centroid[1])}});
        }
      }
    }
  });
  out.tiles_x = kTilesX;
  out.tiles_y = kTilesY;
  out.tile_dx.assign(size_t(kTilesX) * kTilesY * 2, 0.0f);
  out.tile_dy.assign(size_t(kTilesX) * kTilesY * 2, 0.0f);
  for (int axis = 0; axis < 2; ++axis) {
    std::vector<Sample> all;
    for (const std::vector<Sample>& part : local[axis]) {
      all.insert(all.end(), part.begin(), part.end());
    }
    out.edges += int64_t(all.size());
    if (all.size() < kMinSamples) return out;  // too few edges to say: no correction
    std::vector<float>& field = axis == 0 ? out.tile_dx : out.tile_dy;
    for (int c = 0; c < 2; ++c) {
      std::vector<float> v;
      v.reserve(all.size());
      std::vector<std::vector<float>> by_tile(size_t(kTilesX) * kTilesY);
      for (const Sample& s : all) {
        v.push_back(s.offset[c]);
        by_tile[size_t(s.tile)].push_back(s.offset[c]);
      }
      const double global = Median(v);
      (axis == 0 ? out.dx : out.dy)[c == 0 ? 0 : 2] = global;
      for (size_t t = 0; t < by_tile.size(); ++t) {
        field[t * 2 + size_t(c)] =
            float(by_tile[t].size() >= kMinTileSamples ? Median(by_tile[t]) : global);
      }
    }
  }
  for (size_t i = 0; i < out.tile_dx.size(); ++i) {
    out.max_offset_px = std::max(out.max_offset_px, std::hypot(double(out.tile_dx[i]),
                                                               double(out.tile_dy[i])));
  }
  out.found = out.max_offset_px >= kMinOffsetPx;
  return out;
}

int ChannelShiftRowPad(const ChannelShift& shift, int height_px) {
  // A tap lies at most the largest row offset (the field is bilinear between tile offsets) and
  // 2 rows beyond the row read.
  float max_dy = 0.0f;
  for (float dy : shift.tile_dy) max_dy = std::max(max_dy, std::abs(dy));
  return int(std::min<float>(std::ceil(max_dy), float(height_px))) + 3;
}

int64_t CorrectChannelShift(geometry::LinearImage& image, const ChannelShift& shift,
                            geometry::LinearImage* changed, int row_begin, int row_end) {
  const int W = image.width_px, H = image.height_px, C = image.channels;
  if (changed != nullptr) *changed = geometry::LinearImage{};
  if (!shift.found || C < 3 || shift.width_px != W || shift.height_px != H) return 0;
  // A band of the image (LinearImage::row_origin) holds rows [origin, origin + held).
  const int origin = image.row_origin;
  const size_t stride = size_t(W) * C;
  const int held = image.HeldRows();
  row_begin = std::clamp(row_begin, origin, origin + held);
  row_end = row_end < 0 ? origin + held : std::clamp(row_end, row_begin, origin + held);
  if (row_begin == row_end) return 0;
  // The rows as decoded that the corrected ones read (a band must hold them: as of the whole
  // image, clamped to its edges).
  const int pad = ChannelShiftRowPad(shift, H);
  const int band_begin = std::max(0, row_begin - pad), band_end = std::min(H, row_end + pad);
  if (band_begin < origin || band_end > origin + held) return 0;  // not held: left raw
  const std::vector<float> raw(
      image.pixels.begin() + ptrdiff_t(size_t(band_begin - origin) * stride),
      image.pixels.begin() + ptrdiff_t(size_t(band_end - origin) * stride));
  auto at = [&](int x, int y, int c) -> const float& {  // y within the band
    return raw[(size_t(y - band_begin) * W + size_t(x)) * C + size_t(c)];
  };
  auto value = [&](int x, int y, int c) {
    x = shift.wrap ? ((x % W) + W) % W : std::clamp(x, 0, W - 1);
    return at(x, std::clamp(y, band_begin, band_end - 1), c);
  };
  if (changed != nullptr) *changed = internal::ConfidenceOnes(W, H);
  tbb::enumerable_thread_specific<int64_t> counts(0);
  const tbb::blocked_range<int> corrected_rows(row_begin, row_end);
  tbb::parallel_for(corrected_rows, [&](const tbb::blocked_range<int>& rows) {
    int64_t& count = counts.local();
    for (int y = rows.begin(); y != rows.end(); ++y) {
      for (int x = 0; x < W; ++x) {
        const size_t p = size_t(y) * W + size_t(x);
        float level = 0.0f, moved = 0.0f;
        for (int c = 0; c < 3; ++c) level = std::max(level, at(x, y, c));
        for (const int c : {0, 2}) {
          // The channel's content at (x, y) was recorded at (x, y) + its offset.
          const auto [dx, dy] = shift.Offset(c, x + 0.5, y + 0.5);
          const double sx = x + dx, sy = y + dy;
          const int x0 = int(std::floor(sx)), y0 = int(std::floor(sy));
          float kx[4], ky[4];
          CatmullRom(float(sx - x0), kx);
          CatmullRom(float(sy - y0), ky);
          float v = 0.0f;
          if (x0 >= 1 && x0 + 2 < W && y0 >= 1 && y0 + 2 < H) {
            // Inside the image: the 4×4 taps read straight from the rows (the same sums).
            const float* tap = &at(x0 - 1, y0 - 1, c);
            for (int j = 0; j < 4; ++j, tap += stride) {
              float row = 0.0f;
              for (int i = 0; i < 4; ++i) row += kx[i] * tap[size_t(i) * C];
              v += ky[j] * row;
            }
          } else {
            for (int j = 0; j < 4; ++j) {
              float row = 0.0f;
              for (int i = 0; i < 4; ++i) row += kx[i] * value(x0 - 1 + i, y0 - 1 + j, c);
              v += ky[j] * row;
            }
          }
          // The cubic's overshoot at an edge stays within the clip and above 0.
          v = std::clamp(v, 0.0f, image.clip_value);
          moved = std::max(moved, std::abs(v - at(x, y, c)));
          image.pixels[(p - size_t(origin) * W) * C + size_t(c)] = v;
        }
        // What the raw pixel's colour owed to fringing, as a share of its light.
        const float share = moved / std::max(level, 1e-6f * image.clip_value);
        if (share > float(kAffectedShare)) {
          ++count;
          if (changed != nullptr) changed->pixels[p] = std::max(0.0f, 1.0f - share);
        }
      }
    }
  });
  int64_t total = 0;
  for (int64_t c : counts) total += c;
  return total;
}

}  // namespace vasl::ingest

/// @file codec.cc
/// @brief Codec artefacts as per-pixel confidence (VASL-MODEL §9): the error a JPEG's
///        quantisation left in each 8×8 block (blocking and ringing) and its chroma subsampling
///        left at colour edges, from the file's own tables.
#include <algorithm>
#include <array>
#include <cmath>
#include <vector>

#include <tbb/blocked_range.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>

#include "lattice/ingest/artefacts.h"
#include "lattice/ingest/artefacts_internal.h"

namespace vasl::ingest {
namespace {

using internal::kAffectedShare;


/// The IJG (libjpeg) luminance table at quality 50, row-major: the reference a file's table is
/// compared with to name its quality.
constexpr int kIjgLuma[64] = {16, 11, 10, 16, 24,  40,  51,  61,  12, 12, 14,  19,  26,
                              58, 60, 55, 14, 13, 16,  24,  40,  57, 69, 56,  14,  17,
                              22, 29, 51, 87, 80, 62,  18,  22,  37, 56, 68,  109, 103,
                              77, 24, 35, 55, 64, 81,  104, 113, 92, 49, 64,  78,  87,
                              103, 121, 120, 101, 72, 92, 95, 98, 112, 100, 103, 99};

/// The slope dL/dV of the sRGB EOTF (geometry::SrgbToLinear) at an encoded value V in [0, 1].
double LinearPerCode(double v) {
  return v <= 0.04045 ? 1.0 / 12.92 : 2.4 / 1.055 * std::pow((v + 0.055) / 1.055, 1.4);
}

/// The orthonormal 8-point DCT-II basis JPEG uses: c[u][x] = ½·C(u)·cos((2x + 1)uπ/16).
std::array<std::array<double, 8>, 8> DctBasis() {
  std::array<std::array<double, 8>, 8> c{};
  for (int u = 0; u < 8; ++u) {
    for (int x = 0; x < 8; ++x) {
      c[size_t(u)][size_t(x)] =
          0.5 * (u == 0 ? M_SQRT1_2 : 1.0) * std::cos((2 * x + 1) * u * M_PI / 16.0);
    }
  }
  return c;
}

/// E[F² | |F| < a] for a Laplacian of scale b: what a coefficient quantised to 0 lost.
double LostToZero(double a, double b) {
  const double e = b > 0.0 ? std::exp(-a / b) : 0.0;
  return e < 1.0 ? (2.0 * b * b - e * (a * a + 2.0 * a * b + 2.0 * b * b)) / (1.0 - e) : 0.0;
}

/// Per 8×8 block of one plane the codec coded (luma, or a chroma plane at its own resolution),
/// the mean square error its quantisation by `q` left, in code units².
/// @details A coefficient that survived (|F| ≥ q/2; one quantised to 0 reads back near 0) lost
///          q²/12, uniform within its step. One quantised to 0 lost E[F² | |F| < q/2] under a
///          Laplacian whose scale b the share of that frequency's coefficients that survived
///          names (P(|F| < q/2) = 1 − e^(−q/2b)), among blocks of as much detail (surviving AC
///          coefficients 0, 1-2, 3-5, 6-11, 12+): a block with an edge rings more than a smooth
///          one. A block in which no AC coefficient survived is either flat or lost all its
///          detail; its neighbours' DC tell which (a flat region's decode to one DC), so its
///          class's scales are taken in proportion to the DC differences across it. The sum
///          over 64 is the block's mean square error (the DCT is orthonormal).
std::vector<float> PlaneBlockError(const std::vector<float>& plane, int w, int h,
                                   const std::array<uint16_t, 64>& q, float offset) {
  const int bx = (w + 7) / 8, by = (h + 7) / 8;
  const size_t blocks = size_t(bx) * size_t(by);
  std::vector<uint64_t> survived(blocks, 0);  // bit u + 8v: coefficient (u, v) survived
  std::vector<float> dc(blocks, 0.0f);
  const auto basis = DctBasis();
  tbb::parallel_for(tbb::blocked_range<int>(0, by), [&](const tbb::blocked_range<int>& rows) {
    for (int j = rows.begin(); j != rows.end(); ++j) {
      for (int i = 0; i < bx; ++i) {
        double f[8][8];
        for (int y = 0; y < 8; ++y) {
          for (int x = 0; x < 8; ++x) {  // the encoder replicates the edge to fill a block
            const int px = std::min(w - 1, 8 * i + x), py = std::min(h - 1, 8 * j + y);
            f[y][x] = double(plane[size_t(py) * size_t(w) + size_t(px)]) - offset;
          }
        }
        double rows_t[8][8];  // along x, then along y
        for (int y = 0; y < 8; ++y) {
          for (int u = 0; u < 8; ++u) {
            double sum = 0.0;
            for (int x = 0; x < 8; ++x) sum += basis[size_t(u)][size_t(x)] * f[y][x];
            rows_t[y][u] = sum;
          }
        }
        uint64_t mask = 0;
        for (int v = 0; v < 8; ++v) {
          for (int u = 0; u < 8; ++u) {
            double sum = 0.0;
            for (int y = 0; y < 8; ++y) sum += basis[size_t(v)][size_t(y)] * rows_t[y][u];
            if (u == 0 && v == 0) dc[size_t(j) * bx + size_t(i)] = float(sum);
            if (std::abs(sum) >= 0.5 * q[size_t(v * 8 + u)]) mask |= uint64_t{1} << (v * 8 + u);
          }
        }
        survived[size_t(j) * bx + size_t(i)] = mask;
      }
    }
  });
  constexpr int kClasses = 5;
  auto class_of = [](uint64_t mask) {
    const int n = __builtin_popcountll(mask & ~uint64_t{1});
    return n == 0 ? 0 : n <= 2 ? 1 : n <= 5 ? 2 : n <= 11 ? 3 : 4;
  };
  // The DC differences across each block (left to right, top to bottom; edges repeat).
  std::vector<float> context(blocks);
  tbb::parallel_for(0, by, [&](int j) {
    for (int i = 0; i < bx; ++i) {
      auto at = [&](int ii, int jj) {
        const size_t row = size_t(std::clamp(jj, 0, by - 1));
        return double(dc[row * bx + size_t(std::clamp(ii, 0, bx - 1))]);
      };
      const double gx = at(i + 1, j) - at(i - 1, j), gy = at(i, j + 1) - at(i, j - 1);
      context[size_t(j) * bx + size_t(i)] = float(gx * gx + gy * gy);
    }
  });
  std::array<std::array<double, 64>, kClasses> scale{};  // b per class and frequency
  double flat_context = 0.0;                             // class 0's mean DC difference²
  {
    std::array<int64_t, kClasses> in_class{};
    std::array<std::array<int64_t, 64>, kClasses> kept{};
    for (size_t b = 0; b < blocks; ++b) {
      const int c = class_of(survived[b]);
      ++in_class[size_t(c)];
      for (int k = 0; k < 64; ++k) kept[size_t(c)][size_t(k)] += (survived[b] >> k) & 1;
      if (c == 0) flat_context += context[b];
    }
    flat_context /= double(std::max<int64_t>(1, in_class[0]));
    for (int c = 0; c < kClasses; ++c) {
      for (int k = 0; k < 64; ++k) {
        // A frequency that never survived in the class: as if one block more had not either.
        const double zero =
            1.0 - double(kept[size_t(c)][size_t(k)]) / double(in_class[size_t(c)] + 1);
        scale[size_t(c)][size_t(k)] = 0.5 * q[size_t(k)] / -std::log(std::max(1e-12, 1.0 - zero));
      }
    }
  }
  std::vector<float> block_mse(blocks);
  tbb::parallel_for(size_t{0}, blocks, [&](size_t b) {
    const int c = class_of(survived[b]);
    // A class-0 block whose neighbours decode to its own DC lost nothing the image shows; a
    // plane whose every such block is so (a grey image's chroma) lost nothing there at all.
    const double s =
        c != 0 ? 1.0 : flat_context > 0.0 ? std::sqrt(context[b] / flat_context) : 0.0;
    double mse = 0.0;
    for (int k = 0; k < 64; ++k) {
      const double step = q[size_t(k)];
      mse += (survived[b] >> k) & 1 ? step * step / 12.0
                                    : LostToZero(0.5 * step, s * scale[size_t(c)][size_t(k)]);
    }
    block_mse[b] = float(mse / 64.0);
  });
  return block_mse;
}

}  // namespace

double CodecMap::CoveredFraction(int width_px, int height_px) const {
  const double pixels = double(width_px) * double(height_px);
  return pixels > 0.0 ? double(soft_pixels) / pixels : 0.0;
}

CodecMap DetectCodec(const geometry::LinearImage& image) {
  if (image.coded_window && image.coding != nullptr) {
    // A partial panorama placed in its sphere: the codec's blocks start at the file's corner,
    // so the file's part is taken alone and its map placed back (1 elsewhere).
    const geometry::ImageWindow& win = *image.coded_window;
    const size_t C = size_t(std::max(image.channels, 0));
    geometry::LinearImage part;
    part.width_px = win.width_px;
    part.height_px = win.height_px;
    part.channels = image.channels;
    part.clip_value = image.clip_value;
    part.coding = image.coding;
    part.pixels.resize(size_t(win.width_px) * size_t(win.height_px) * C);
    for (int j = 0; j < win.height_px; ++j) {
      std::copy_n(&image.pixels[(size_t(j + win.top_px) * size_t(image.width_px) +
                                 size_t(win.left_px)) * C],
                  size_t(win.width_px) * C, &part.pixels[size_t(j) * size_t(win.width_px) * C]);
    }
    CodecMap out = DetectCodec(part);
    if (out.conf.pixels.empty()) return out;
    geometry::LinearImage conf = internal::ConfidenceOnes(image.width_px, image.height_px);
    for (int j = 0; j < win.height_px; ++j) {
      std::copy_n(&out.conf.pixels[size_t(j) * size_t(win.width_px)], size_t(win.width_px),
                  &conf.pixels[size_t(j + win.top_px) * size_t(image.width_px) +
                               size_t(win.left_px)]);
    }
    out.conf = std::move(conf);
    return out;
  }
  CodecMap out;
  const int W = image.width_px, H = image.height_px, C = image.channels;
  if (image.coding == nullptr || W <= 0 || H <= 0 || (C != 1 && C != 3) ||
      image.pixels.size() != size_t(W) * size_t(H) * size_t(C) || !(image.clip_value > 0.0f)) {
    return out;
  }
  const geometry::BlockCoding& coding = *image.coding;
  out.jpeg = true;
  // The quality an IJG encoder would have been given for this luma table (its scale S = 100·q /
  // q50 per step, median; S = 5000 / Q below 50, 200 − 2Q above).
  {
    std::vector<double> scale;
    for (int i = 0; i < 64; ++i) scale.push_back(100.0 * coding.luma_q[size_t(i)] / kIjgLuma[i]);
    std::nth_element(scale.begin(), scale.begin() + 32, scale.end());
    const double s = scale[32];
    out.quality = std::clamp(s >= 100.0 ? 5000.0 / s : (200.0 - s) / 2.0, 1.0, 100.0);
  }
  const int rx = std::max(1, coding.chroma_step_x), ry = std::max(1, coding.chroma_step_y);
  out.chroma_subsampled = rx > 1 || ry > 1;
  const float inv_clip = 1.0f / image.clip_value;
  // The image back in the codec's domain: 8-bit sRGB codes, as Y'CbCr (JFIF).
  const size_t n = size_t(W) * size_t(H);
  std::vector<float> luma(n), cb(n), cr(n);
  tbb::parallel_for(tbb::blocked_range<size_t>(0, n, 1 << 14),
                    [&](const tbb::blocked_range<size_t>& r) {
                      for (size_t p = r.begin(); p != r.end(); ++p) {
                        double v[3];
                        for (int c = 0; c < 3; ++c) {
                          const float l = image.pixels[p * size_t(C) + size_t(C == 3 ? c : 0)];
                          v[c] = 255.0 * geometry::LinearToSrgb(l * inv_clip);
                        }
                        luma[p] = float(0.299 * v[0] + 0.587 * v[1] + 0.114 * v[2]);
                        cb[p] = float(-0.168736 * v[0] - 0.331264 * v[1] + 0.5 * v[2]);
                        cr[p] = float(0.5 * v[0] - 0.418688 * v[1] - 0.081312 * v[2]);
                      }
                    });
  // Blocking and ringing: each plane's quantisation error per block. The chroma planes are
  // coded at their own resolution (the mean over a chroma sample's pixels, as the encoder took).
  const std::vector<float> luma_mse = PlaneBlockError(luma, W, H, coding.luma_q, 128.0f);
  const int cw = (W + rx - 1) / rx, ch = (H + ry - 1) / ry;
  std::vector<float> cb_mse, cr_mse;
  if (C == 3) {
    std::vector<float> sub_b(size_t(cw) * size_t(ch)), sub_r(sub_b.size());
    tbb::parallel_for(0, ch, [&](int y) {
      for (int x = 0; x < cw; ++x) {
        double sb = 0.0, sr = 0.0;
        int count = 0;
        for (int yy = y * ry; yy < std::min(H, y * ry + ry); ++yy) {
          for (int xx = x * rx; xx < std::min(W, x * rx + rx); ++xx) {
            sb += cb[size_t(yy) * W + size_t(xx)], sr += cr[size_t(yy) * W + size_t(xx)];
            ++count;
          }
        }
        sub_b[size_t(y) * cw + size_t(x)] = float(sb / count);
        sub_r[size_t(y) * cw + size_t(x)] = float(sr / count);
      }
    });
    cb_mse = PlaneBlockError(sub_b, cw, ch, coding.chroma_q, 0.0f);
    cr_mse = PlaneBlockError(sub_r, cw, ch, coding.chroma_q, 0.0f);
  }
  // Per pixel, each channel's error (R' = Y' + 1.402 Cr, G' = Y' − 0.344 Cb − 0.714 Cr,
  // B' = Y' + 1.772 Cb): the planes' block errors in quadrature and, under subsampled chroma,
  // what the averaging took from a colour edge: the decoder's chroma runs as a ramp across the
  // edge, so a pixel's own chroma lies from the edge's nearer side by as much as it lost (the
  // signed distance to the nearer of the chroma's extremes within a chroma sample's reach on
  // each side). Each channel's error in linear terms at its own level; the largest over the
  // pixel's light is the share.
  out.conf = internal::ConfidenceOnes(W, H);
  const int bx = (W + 7) / 8, cbx = (cw + 7) / 8;
  const bool subsampled = C == 3 && out.chroma_subsampled;
  constexpr double kR = 1.402, kGb = 0.344136, kGr = 0.714136, kB = 1.772;
  const double cut = 1.0 - 1.0 / (1.0 + kAffectedShare);  // a share over it lowers the pixel
  tbb::enumerable_thread_specific<int64_t> counts(0);
  tbb::parallel_for(tbb::blocked_range<int>(0, H), [&](const tbb::blocked_range<int>& rows) {
    int64_t& count = counts.local();
    std::vector<float> lo_b(subsampled ? W : 0), hi_b(lo_b.size()), lo_r(lo_b.size()),
        hi_r(lo_b.size());
    for (int y = rows.begin(); y != rows.end(); ++y) {
      if (subsampled) {  // each column's extremes over the rows within reach
        for (int x = 0; x < W; ++x) {
          const size_t p = size_t(y) * W + size_t(x);
          lo_b[size_t(x)] = hi_b[size_t(x)] = cb[p], lo_r[size_t(x)] = hi_r[size_t(x)] = cr[p];
        }
        for (int yy = std::max(0, y - ry); yy <= std::min(H - 1, y + ry); ++yy) {
          for (int x = 0; x < W; ++x) {
            const size_t q = size_t(yy) * W + size_t(x);
            lo_b[size_t(x)] = std::min(lo_b[size_t(x)], cb[q]);
            hi_b[size_t(x)] = std::max(hi_b[size_t(x)], cb[q]);
            lo_r[size_t(x)] = std::min(lo_r[size_t(x)], cr[q]);
            hi_r[size_t(x)] = std::max(hi_r[size_t(x)], cr[q]);
          }
        }
      }
      for (int x = 0; x < W; ++x) {
        const size_t p = size_t(y) * W + size_t(x);
        const double y2 = luma_mse[size_t(y / 8) * bx + size_t(x / 8)];
        double e2[3] = {y2, y2, y2};
        if (C == 3) {
          const size_t cblk = size_t(y / ry / 8) * cbx + size_t(x / rx / 8);
          double db = 0.0, dr = 0.0;
          if (subsampled) {
            float b0 = cb[p], b1 = cb[p], r0 = cr[p], r1 = cr[p];
            for (int xx = std::max(0, x - rx); xx <= std::min(W - 1, x + rx); ++xx) {
              b0 = std::min(b0, lo_b[size_t(xx)]), b1 = std::max(b1, hi_b[size_t(xx)]);
              r0 = std::min(r0, lo_r[size_t(xx)]), r1 = std::max(r1, hi_r[size_t(xx)]);
            }
            db = cb[p] - b0 < b1 - cb[p] ? cb[p] - b0 : cb[p] - b1;
            dr = cr[p] - r0 < r1 - cr[p] ? cr[p] - r0 : cr[p] - r1;
          }
          const double qb = cb_mse[cblk], qr = cr_mse[cblk];
          e2[0] += kR * kR * (dr * dr + qr);
          e2[1] += (kGb * db + kGr * dr) * (kGb * db + kGr * dr) + kGb * kGb * qb + kGr * kGr * qr;
          e2[2] += kB * kB * (db * db + qb);
        }
        const double level = std::max(1e-6, double(internal::Level(image, p)));
        const double codes[3] = {luma[p] + kR * cr[p], luma[p] - kGb * cb[p] - kGr * cr[p],
                                 luma[p] + kB * cb[p]};
        const int channels = C == 3 ? 3 : 1;
        // The steepest channel bounds the share: most pixels are settled by it alone.
        double vmax = 0.0, emax = 0.0;
        for (int c = 0; c < channels; ++c) {
          vmax = std::max(vmax, codes[c]);
          emax = std::max(emax, e2[c]);
        }
        const auto slope = [](double code) {
          return LinearPerCode(std::clamp(code, 0.0, 255.0) / 255.0) / 255.0;
        };
        if (std::sqrt(emax) * slope(vmax) / level <= cut) continue;
        double share = 0.0;
        for (int c = 0; c < channels; ++c) {
          share = std::max(share, std::sqrt(e2[c]) * slope(codes[c]) / level);
        }
        if (share <= cut) continue;
        out.conf.pixels[p] = float(std::max(0.0, 1.0 - share));
        ++count;
      }
    }
  });
  for (int64_t c : counts) out.soft_pixels += c;
  return out;
}

}  // namespace vasl::ingest

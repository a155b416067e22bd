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

}  // namespace

double CodecMap::CoveredFraction(int width_px, int height_px) const {
  const double pixels = double(width_px) * double(height_px);
  return pixels > 0.0 ? double(soft_pixels) / pixels : 0.0;
}

CodecMap DetectCodec(const geometry::LinearImage& image) {
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
  out.chroma_subsampled = coding.chroma_step_x > 1 || coding.chroma_step_y > 1;
  const float inv_clip = 1.0f / image.clip_value;
  // The image back in the codec's domain: 8-bit sRGB codes, as Y'CbCr (JFIF).
  const size_t n = size_t(W) * size_t(H);
  std::vector<float> luma(n), cb(n), cr(n), code_max(n);
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
                        code_max[p] = float(std::max({v[0], v[1], v[2]}));
                      }
                    });
  // Per 8×8 block (the codec's grid from the image's corner): its luma coefficients again, and
  // which survived quantisation (|F| ≥ q/2; one quantised to 0 reads back near 0).
  const int bx = (W + 7) / 8, by = (H + 7) / 8;
  const size_t blocks = size_t(bx) * size_t(by);
  std::vector<uint64_t> survived(blocks, 0);  // bit u + 8v: coefficient (u, v) survived
  const auto basis = DctBasis();
  tbb::parallel_for(tbb::blocked_range<int>(0, by), [&](const tbb::blocked_range<int>& rows) {
    for (int j = rows.begin(); j != rows.end(); ++j) {
      for (int i = 0; i < bx; ++i) {
        double f[8][8];
        for (int y = 0; y < 8; ++y) {
          for (int x = 0; x < 8; ++x) {  // the encoder replicates the edge to fill a block
            const int px = std::min(W - 1, 8 * i + x), py = std::min(H - 1, 8 * j + y);
            f[y][x] = double(luma[size_t(py) * W + size_t(px)]) - 128.0;
          }
        }
        double rows_t[8][8];  // along x, then along y
        for (int y = 0; y < 8; ++y) {
          for (int u = 0; u < 8; ++u) {
            double s = 0.0;
            for (int x = 0; x < 8; ++x) s += basis[size_t(u)][size_t(x)] * f[y][x];
            rows_t[y][u] = s;
          }
        }
        uint64_t mask = 0;
        for (int v = 0; v < 8; ++v) {
          for (int u = 0; u < 8; ++u) {
            double s = 0.0;
            for (int y = 0; y < 8; ++y) s += basis[size_t(v)][size_t(y)] * rows_t[y][u];
            if (std::abs(s) >= 0.5 * coding.luma_q[size_t(v * 8 + u)]) {
              mask |= uint64_t{1} << (v * 8 + u);
            }
          }
        }
        survived[size_t(j) * bx + size_t(i)] = mask;
      }
    }
  });
  // Each frequency's coefficients follow a Laplacian over blocks alike, whose scale b the share
  // that survived names (P(|F| < q/2) = 1 − e^(−q/2b)); a coefficient quantised to 0
  // lost E[F² | |F| < q/2] of it; one that survived lost q²/12 (uniform within its step). Blocks
  // are alike by their surviving AC coefficients (classes 0, 1-2, 3-5, 6-11, 12+): a block with
  // an edge lost larger coefficients (ringing) than a smooth one. The sum over 64 is the
  // block's mean square error (the DCT is orthonormal).
  constexpr int kClasses = 5;
  auto class_of = [](uint64_t mask) {
    const int n = __builtin_popcountll(mask & ~uint64_t{1});
    return n == 0 ? 0 : n <= 2 ? 1 : n <= 5 ? 2 : n <= 11 ? 3 : 4;
  };
  std::array<std::array<double, 64>, kClasses> lost_mse{};
  {
    std::array<int64_t, kClasses> in_class{};
    std::array<std::array<int64_t, 64>, kClasses> kept{};
    for (uint64_t m : survived) {
      const int c = class_of(m);
      ++in_class[size_t(c)];
      for (int k = 0; k < 64; ++k) kept[size_t(c)][size_t(k)] += (m >> k) & 1;
    }
    for (int c = 0; c < kClasses; ++c) {
      for (int k = 0; k < 64; ++k) {
        const double a = 0.5 * coding.luma_q[size_t(k)];
        // A frequency that never survived in the class: as if one block more had not either.
        const double zero =
            1.0 - double(kept[size_t(c)][size_t(k)]) / double(in_class[size_t(c)] + 1);
        const double b = a / -std::log(std::max(1e-12, 1.0 - zero));
        const double e = std::exp(-a / b);
        lost_mse[size_t(c)][size_t(k)] =
            e < 1.0 ? (2.0 * b * b - e * (a * a + 2.0 * a * b + 2.0 * b * b)) / (1.0 - e) : 0.0;
      }
    }
  }
  std::vector<float> block_mse(blocks);
  tbb::parallel_for(size_t{0}, blocks, [&](size_t blk) {
    const int c = class_of(survived[blk]);
    double mse = 0.0;
    for (int k = 0; k < 64; ++k) {
      const double q = coding.luma_q[size_t(k)];
      mse += (survived[blk] >> k) & 1 ? q * q / 12.0 : lost_mse[size_t(c)][size_t(k)];
    }
    block_mse[blk] = float(mse / 64.0);
  });


  // Per pixel: the block's luma error and, under subsampled chroma, half the chroma's range
  // within a chroma sample's reach (a colour edge the codec averaged), as the largest channel
  // error (R' = Y' + 1.402 Cr, B' = Y' + 1.772 Cb); over the pixel's light in linear terms.
  out.conf = internal::ConfidenceOnes(W, H);
  const int rx = coding.chroma_step_x, ry = coding.chroma_step_y;
  tbb::enumerable_thread_specific<int64_t> counts(0);
  tbb::parallel_for(tbb::blocked_range<int>(0, H), [&](const tbb::blocked_range<int>& rows) {
    int64_t& count = counts.local();
    for (int y = rows.begin(); y != rows.end(); ++y) {
      for (int x = 0; x < W; ++x) {
        const size_t p = size_t(y) * W + size_t(x);
        double err2 = block_mse[size_t(y / 8) * bx + size_t(x / 8)];
        if (out.chroma_subsampled) {
          float lo_b = cb[p], hi_b = cb[p], lo_r = cr[p], hi_r = cr[p];
          for (int yy = std::max(0, y - ry / 2); yy <= std::min(H - 1, y + ry / 2); ++yy) {
            for (int xx = std::max(0, x - rx / 2); xx <= std::min(W - 1, x + rx / 2); ++xx) {
              const size_t q = size_t(yy) * W + size_t(xx);
              lo_b = std::min(lo_b, cb[q]), hi_b = std::max(hi_b, cb[q]);
              lo_r = std::min(lo_r, cr[q]), hi_r = std::max(hi_r, cr[q]);
            }
          }
          const double e = std::max(1.772 * 0.5 * (hi_b - lo_b), 1.402 * 0.5 * (hi_r - lo_r));
          err2 += e * e;
        }
        const double v = code_max[p] / 255.0;
        const double level = std::max(1e-6, double(geometry::SrgbToLinear(float(v))));
        const double share = std::sqrt(err2) / 255.0 * LinearPerCode(v) / level;
        if (1.0 - share >= 1.0 / (1.0 + kAffectedShare)) continue;
        out.conf.pixels[p] = float(std::max(0.0, 1.0 - share));
        ++count;
      }
    }
  });
  for (int64_t c : counts) out.soft_pixels += c;
  return out;
}

}  // namespace vasl::ingest

// VASL-MODEL §9, codec: sharp textures and colour edges encoded as low-quality JPEG (4:2:0
// chroma) through OpenImageIO and decoded as ingest decodes them; the file's tables are read,
// the codec map finds the 8×8 blocks whose pixels the codec moved by more than a tenth of their
// light (precision, recall), a high-quality JPEG is barely touched and a PNG not at all, and a
// confidence-weighted blend moves the damaged pixels' colour toward the truth.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "lattice/ingest/artefacts.h"
#include "lattice/ingest/sources.h"
#include "tests/ingest/encode_srgb8.h"
#include "tests/ingest/planted_panorama.h"

namespace vasl::ingest {
namespace {

/// The planted textures with colour: the checkers' lower half tinted in bands of saturated
/// colour (red, green, blue, yellow; 23 px wide), whose edges chroma subsampling smears.
geometry::LinearImage ColourTextures(int w, int h) {
  geometry::LinearImage img = MakePanorama(w, h, {}, false).image;
  const float tint[4][3] = {{0.9f, 0.15f, 0.1f}, {0.1f, 0.8f, 0.15f}, {0.1f, 0.2f, 0.9f},
                            {0.85f, 0.8f, 0.1f}};
  for (int y = h / 4; y < h / 2; ++y) {
    for (int x = 0; x < w; ++x) {
      const float* t = tint[(x / 23) % 4];
      for (int c = 0; c < 3; ++c) img.pixels[3 * (size_t(y) * w + x) + c] *= 2.0f * t[c];
    }
  }
  for (float& v : img.pixels) v = std::min(v, 0.98f);
  return img;
}

/// Per 8×8 block, the root mean square of its pixels' shares.
std::vector<double> BlockRms(int w, int h, const std::vector<double>& share) {
  const int bx = (w + 7) / 8, by = (h + 7) / 8;
  std::vector<double> rms(size_t(bx) * size_t(by), 0.0);
  std::vector<int> all(rms.size(), 0);
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      const size_t b = size_t(y / 8) * bx + size_t(x / 8);
      const double s = share[size_t(y) * w + x];
      ++all[b];
      rms[b] += s * s;
    }
  }
  for (size_t b = 0; b < rms.size(); ++b) rms[b] = std::sqrt(rms[b] / all[b]);
  return rms;
}

/// The largest channel error of each pixel of `decoded` against `truth`, over truth's light.
std::vector<double> ErrorShare(const geometry::LinearImage& decoded,
                               const geometry::LinearImage& truth) {
  std::vector<double> share(size_t(truth.width_px) * truth.height_px);
  const size_t C = size_t(truth.channels), D = size_t(decoded.channels);  // grey may decode as RGB
  for (size_t p = 0; p < share.size(); ++p) {
    float err = 0.0f, level = 0.0f;
    for (size_t c = 0; c < C; ++c) {
      err = std::max(err, std::abs(decoded.pixels[D * p + c] - truth.pixels[C * p + c]));
      level = std::max(level, truth.pixels[C * p + c]);
    }
    share[p] = err / std::max(level, 1e-4f);
  }
  return share;
}

// Claim (§9): the JPEG's own tables are read: its luma table names the quality it was written
// at (±2), its chroma is 4:2:0; a PNG has none.
TEST(CodecTest, ReadsTheFilesTablesAndSubsampling) {
  const geometry::LinearImage img = ColourTextures(256, 128);
  for (const int quality : {15, 50, 90}) {
    auto decoded = DecodeImage(EncodeSrgb8(img, "jpg", quality), false, 1 << 20);
    ASSERT_TRUE(decoded.ok()) << decoded.status();
    ASSERT_NE(decoded->coding, nullptr);
    const CodecMap map = DetectCodec(*decoded);
    std::printf("written at quality %d: read as %.1f, chroma %dx%d\n", quality, map.quality,
                decoded->coding->chroma_step_x, decoded->coding->chroma_step_y);
    EXPECT_NEAR(map.quality, quality, 2.0);
    EXPECT_TRUE(map.chroma_subsampled);
    EXPECT_EQ(decoded->coding->chroma_step_x, 2);
    EXPECT_EQ(decoded->coding->chroma_step_y, 2);
  }
  auto png = DecodeImage(EncodeSrgb8(img, "png", 0), false, 1 << 20);
  ASSERT_TRUE(png.ok()) << png.status();
  EXPECT_EQ(png->coding, nullptr);
  EXPECT_TRUE(DetectCodec(*png).conf.pixels.empty());
}

// Claim (§9): the blocks whose pixels the codec moved by more than a tenth of their light (root
// mean square over the block; blocks within ±25% of that not scored) are those where the map
// says so (the root mean square of its 1 − conf over the block over a tenth): at quality 15
// (72% of the blocks damaged, by blocking and ringing) and at quality 95 (8%, at colour edges
// the 4:2:0 chroma smeared) precision and recall ≥ 0.9. Qualities between are printed.
TEST(CodecTest, CodecMapFindsTheBlocksTheCodecDamaged) {
  const int w = 1024, h = 512;
  const geometry::LinearImage truth = ColourTextures(w, h);
  for (const int quality : {15, 30, 50, 75, 95}) {
    auto decoded = DecodeImage(EncodeSrgb8(truth, "jpg", quality), false, 1 << 22);
    ASSERT_TRUE(decoded.ok()) << decoded.status();
    const CodecMap map = DetectCodec(*decoded);
    ASSERT_EQ(map.conf.pixels.size(), size_t(w) * h);
    std::vector<double> said_share(map.conf.pixels.size());
    for (size_t p = 0; p < said_share.size(); ++p) said_share[p] = 1.0 - map.conf.pixels[p];
    const std::vector<double> true_share = ErrorShare(*decoded, truth);
    const std::vector<double> is = BlockRms(w, h, true_share), said = BlockRms(w, h, said_share);
    int64_t truth_blocks = 0, found = 0, both = 0;
    for (size_t b = 0; b < is.size(); ++b) {
      if ((is[b] > 0.1 / 1.25) != (is[b] > 0.1 * 1.25)) continue;
      const bool damaged = is[b] > 0.1, flagged = said[b] > 0.1;
      truth_blocks += damaged, found += flagged, both += damaged && flagged;
    }
    const double precision = double(both) / double(std::max<int64_t>(1, found));
    const double recall = double(both) / double(std::max<int64_t>(1, truth_blocks));
    std::printf("quality %d: %lld of %zu blocks damaged, %lld found, %lld both: precision "
                "%.3f, recall %.3f; %.2f%% of the image below 1\n",
                quality, (long long)truth_blocks, is.size(), (long long)found, (long long)both,
                precision, recall, 100.0 * map.CoveredFraction(w, h));
    if (quality != 15 && quality != 95) continue;
    EXPECT_GT(truth_blocks, 300);
    EXPECT_GE(precision, 0.9);
    EXPECT_GE(recall, 0.9);
  }
}

// Claim (§9): the map is whole on any JPEG the decoder gives: sizes that are no multiple of the
// 8×8 or 16×16 blocks, grey images and full-resolution (4:4:4) chroma. Each map covers its
// image in [0, 1] and finds the damaged blocks at quality 15 as it does on the 4:2:0 image
// (precision and recall ≥ 0.8, printed).
TEST(CodecTest, OddSizesGreyAndFullChroma) {
  const int w = 333, h = 171;
  const geometry::LinearImage colour = ColourTextures(w, h);
  geometry::LinearImage grey = colour;
  grey.channels = 1;
  grey.pixels.resize(size_t(w) * h);
  for (size_t p = 0; p < grey.pixels.size(); ++p) grey.pixels[p] = colour.pixels[3 * p + 1];
  struct Case {
    const char* name;
    const geometry::LinearImage* truth;
    const char* subsampling;
  };
  for (const Case& c : {Case{"grey", &grey, ""}, Case{"4:4:4", &colour, "4:4:4"},
                        Case{"4:2:2", &colour, "4:2:2"}}) {
    auto decoded = DecodeImage(EncodeSrgb8(*c.truth, "jpg", 15, c.subsampling), false, 1 << 20);
    ASSERT_TRUE(decoded.ok()) << c.name << ": " << decoded.status();
    ASSERT_NE(decoded->coding, nullptr) << c.name;
    const CodecMap map = DetectCodec(*decoded);
    ASSERT_EQ(map.conf.pixels.size(), size_t(w) * h) << c.name;
    int64_t out_of_range = 0;
    for (float v : map.conf.pixels) out_of_range += !(v >= 0.0f && v <= 1.0f);
    EXPECT_EQ(out_of_range, 0) << c.name;
    std::printf("%s, %dx%d, chroma %dx%d: %.1f%% of the image below 1\n", c.name, w, h,
                decoded->coding->chroma_step_x, decoded->coding->chroma_step_y,
                100.0 * map.CoveredFraction(w, h));
    EXPECT_EQ(map.chroma_subsampled, std::string(c.subsampling) == "4:2:2") << c.name;
    std::vector<double> said(map.conf.pixels.size());
    for (size_t p = 0; p < said.size(); ++p) said[p] = 1.0 - map.conf.pixels[p];
    const std::vector<double> is = BlockRms(w, h, ErrorShare(*decoded, *c.truth));
    const std::vector<double> says = BlockRms(w, h, said);
    int64_t damaged = 0, found = 0, both = 0;
    for (size_t b = 0; b < is.size(); ++b) {
      if ((is[b] > 0.1 / 1.25) != (is[b] > 0.1 * 1.25)) continue;
      damaged += is[b] > 0.1, found += says[b] > 0.1, both += is[b] > 0.1 && says[b] > 0.1;
    }
    const double precision = double(both) / double(std::max<int64_t>(1, found));
    const double recall = double(both) / double(std::max<int64_t>(1, damaged));
    std::printf("  %lld blocks damaged, precision %.3f, recall %.3f\n", (long long)damaged,
                precision, recall);
    EXPECT_GT(damaged, 100) << c.name;
    EXPECT_GE(precision, 0.8) << c.name;
    EXPECT_GE(recall, 0.8) << c.name;
  }
}

// Claim (§7 with §9): blending the quality-15 view with a clean view of the same surface,
// weighted by conf^κ, moves the damaged pixels' colour toward the truth: κ = 1 lowers the mean
// error of the blend that ignores the map, and κ = 2 brings it under 0.85 of it.
TEST(CodecTest, ConfidenceWeightingMovesDamagedColourTowardTheTruth) {
  const int w = 1024, h = 512;
  const geometry::LinearImage truth = ColourTextures(w, h);
  auto decoded = DecodeImage(EncodeSrgb8(truth, "jpg", 15), false, 1 << 22);
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  const CodecMap map = DetectCodec(*decoded);
  const std::vector<double> share = ErrorShare(*decoded, truth);
  double err[3] = {0.0, 0.0, 0.0};
  int64_t pixels = 0;
  for (size_t p = 0; p < share.size(); ++p) {
    if (!(share[p] > 0.1)) continue;
    for (int kappa = 0; kappa < 3; ++kappa) {
      const double wgt = std::pow(double(map.conf.pixels[p]), kappa);
      for (int c = 0; c < 3; ++c) {
        const double a = decoded->pixels[3 * p + c], t = truth.pixels[3 * p + c];
        err[kappa] += std::abs((wgt * a + t) / (wgt + 1.0) - t) / 3.0;
      }
    }
    ++pixels;
  }
  for (double& e : err) e /= double(std::max<int64_t>(1, pixels));
  std::printf("two-view blend over %lld damaged pixels: mean |error| %.4f ignoring the map, "
              "%.4f with kappa 1, %.4f with kappa 2\n", (long long)pixels, err[0], err[1], err[2]);
  EXPECT_GT(pixels, 10000);
  EXPECT_LT(err[1], err[0]);
  EXPECT_LT(err[2], err[1]);
  EXPECT_LT(err[2], 0.85 * err[0]);
}

}  // namespace
}  // namespace vasl::ingest

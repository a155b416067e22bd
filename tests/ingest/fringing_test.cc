// VASL-MODEL §9, chromatic fringing: red and blue planted at known offsets against green (one
// shift over the image, and a shift that grows across it as lateral chromatic aberration does
// toward a lens's rim) on sharp textures; the estimated offsets match the planted ones, the
// pixels the correction moves are those the shift moved (precision, recall), the correction
// brings the colour at edges back toward the truth, and clean images are left untouched.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <functional>
#include <vector>

#include <gtest/gtest.h>

#include "lattice/ingest/artefacts.h"
#include "tests/ingest/planted_panorama.h"

namespace vasl::ingest {
namespace {

/// `truth` with red and blue resampled (bilinear, columns wrapping) so that each channel's
/// content lies at its offset (dx, dy)(x, y) from where it belongs.
geometry::LinearImage Shifted(
    const geometry::LinearImage& truth,
    const std::function<std::pair<double, double>(int channel, double x, double y)>& offset) {
  geometry::LinearImage out = truth;
  const int W = truth.width_px, H = truth.height_px;
  auto at = [&](int x, int y, int c) {
    x = ((x % W) + W) % W;
    y = std::clamp(y, 0, H - 1);
    return truth.pixels[(size_t(y) * W + size_t(x)) * 3 + size_t(c)];
  };
  for (int y = 0; y < H; ++y) {
    for (int x = 0; x < W; ++x) {
      for (const int c : {0, 2}) {
        const auto [dx, dy] = offset(c, x + 0.5, y + 0.5);
        const double sx = x - dx, sy = y - dy;
        const int x0 = int(std::floor(sx)), y0 = int(std::floor(sy));
        const float fx = float(sx - x0), fy = float(sy - y0);
        out.pixels[(size_t(y) * W + size_t(x)) * 3 + size_t(c)] =
            (1 - fy) * ((1 - fx) * at(x0, y0, c) + fx * at(x0 + 1, y0, c)) +
            fy * ((1 - fx) * at(x0, y0 + 1, c) + fx * at(x0 + 1, y0 + 1, c));
      }
    }
  }
  return out;
}

/// `image` seen through a lens: a 3×3 binomial blur (σ ≈ 0.7 px; columns wrap), so that its
/// edges are as sharp as optics make them rather than one-pixel steps a resampling aliases.
geometry::LinearImage ThroughALens(const geometry::LinearImage& image) {
  geometry::LinearImage out = image;
  const int W = image.width_px, H = image.height_px, C = image.channels;
  const float k[3] = {0.25f, 0.5f, 0.25f};
  for (int y = 0; y < H; ++y) {
    for (int x = 0; x < W; ++x) {
      for (int c = 0; c < C; ++c) {
        float v = 0.0f;
        for (int j = -1; j <= 1; ++j) {
          for (int i = -1; i <= 1; ++i) {
            const int xx = ((x + i) % W + W) % W, yy = std::clamp(y + j, 0, H - 1);
            v += k[i + 1] * k[j + 1] * image.pixels[(size_t(yy) * W + size_t(xx)) * C + size_t(c)];
          }
        }
        out.pixels[(size_t(y) * W + size_t(x)) * C + size_t(c)] = v;
      }
    }
  }
  return out;
}

/// The largest channel difference of pixel p between two images, over `truth`'s light.
double MovedShare(const geometry::LinearImage& a, const geometry::LinearImage& truth, size_t p) {
  float moved = 0.0f, level = 0.0f;
  for (int c = 0; c < 3; ++c) {
    moved = std::max(moved, std::abs(a.pixels[3 * p + c] - truth.pixels[3 * p + c]));
    level = std::max(level, truth.pixels[3 * p + c]);
  }
  return moved / std::max(level, 1e-6f);
}

// Claim (§9): one shift over the image (red +1.2, +0.6 px; blue −0.8, −0.5 px) is measured to
// 0.15 px image-wide and 0.25 px in every tile; the pixels the correction moves by over a tenth
// of their light are those the shift moved by that much (precision and recall ≥ 0.9, a moved
// share within ±20% of a tenth not scored); and over the checkers' edges the mean colour error
// against the truth falls by at least 70%.
TEST(FringingTest, PlantedShiftIsMeasuredAndCorrected) {
  const int w = 2048, h = 1024;
  const geometry::LinearImage truth = ThroughALens(MakePanorama(w, h, {}, false).image);
  const double planted[3][2] = {{1.2, 0.6}, {0.0, 0.0}, {-0.8, -0.5}};
  const geometry::LinearImage shifted = Shifted(truth, [&](int c, double, double) {
    return std::make_pair(planted[c][0], planted[c][1]);
  });
  const ChannelShift shift = EstimateChannelShift(shifted, /*wrap=*/true);
  std::printf("estimate: found %d, %lld edge samples, red (%+.3f, %+.3f), blue (%+.3f, %+.3f)\n",
              int(shift.found), (long long)shift.edges, shift.dx[0], shift.dy[0], shift.dx[2],
              shift.dy[2]);
  ASSERT_TRUE(shift.found);
  double worst_tile = 0.0;
  for (int t = 0; t < shift.tiles_x * shift.tiles_y; ++t) {
    for (int c = 0; c < 2; ++c) {
      const int ch = c == 0 ? 0 : 2;
      const size_t at = size_t(t) * 2 + size_t(c);
      worst_tile = std::max({worst_tile, std::abs(shift.tile_dx[at] - planted[ch][0]),
                             std::abs(shift.tile_dy[at] - planted[ch][1])});
    }
  }
  geometry::LinearImage corrected = shifted, moved_map;
  const int64_t moved = CorrectChannelShift(corrected, shift, &moved_map);
  int64_t truth_px = 0, found = 0, both = 0;
  double err_before = 0.0, err_after = 0.0;
  int64_t edge_px = 0;
  for (size_t p = 0; p < size_t(w) * h; ++p) {
    const double share = MovedShare(shifted, truth, p);
    const bool said = moved_map.pixels[p] < 1.0f;
    const bool is = share > 0.1;
    if ((share > 0.1 / 1.2) == (share > 0.1 * 1.2)) {  // outside the tolerance band
      truth_px += is;
      found += said;
      both += is && said;
    }
    if (int(p / w) < h / 2 && share > 0.1) {  // the checkers' edges
      for (int c = 0; c < 3; ++c) {
        err_before += std::abs(shifted.pixels[3 * p + c] - truth.pixels[3 * p + c]);
        err_after += std::abs(corrected.pixels[3 * p + c] - truth.pixels[3 * p + c]);
      }
      ++edge_px;
    }
  }
  const double precision = double(both) / double(std::max<int64_t>(1, found));
  const double recall = double(both) / double(std::max<int64_t>(1, truth_px));
  std::printf("fringing: %lld edge samples; red (%+.3f, %+.3f) px, blue (%+.3f, %+.3f) px "
              "(planted (+1.2, +0.6), (-0.8, -0.5)); worst tile off by %.3f px; %lld pixels "
              "moved: %lld planted / %lld found / %lld both, precision %.3f, recall %.3f; "
              "checkers' edges (%lld px): mean |error| %.4f before, %.4f after\n",
              (long long)shift.edges, shift.dx[0], shift.dy[0], shift.dx[2], shift.dy[2],
              worst_tile, (long long)moved, (long long)truth_px, (long long)found,
              (long long)both, precision, recall, (long long)edge_px, err_before / edge_px / 3,
              err_after / edge_px / 3);
  for (int c : {0, 2}) {
    EXPECT_NEAR(shift.dx[c], planted[c][0], 0.15) << "channel " << c;
    EXPECT_NEAR(shift.dy[c], planted[c][1], 0.15) << "channel " << c;
  }
  EXPECT_LE(worst_tile, 0.25);
  EXPECT_GT(truth_px, 20000);
  EXPECT_GE(precision, 0.9);
  EXPECT_GE(recall, 0.9);
  EXPECT_GT(edge_px, 10000);
  EXPECT_LT(err_after, 0.3 * err_before);
}

// Claim: a correction of some rows (a revisit's camera, whose samples read only those) gives
// those rows exactly the whole correction's values and leaves every other row raw; the pixels
// it counts are the whole correction's in those rows.
TEST(FringingTest, CorrectingSomeRowsGivesTheWholeCorrectionThere) {
  const int w = 1024, h = 512;
  const geometry::LinearImage truth = ThroughALens(MakePanorama(w, h, {}, false).image);
  const double planted[3][2] = {{1.2, 0.6}, {0.0, 0.0}, {-0.8, -0.5}};
  const geometry::LinearImage shifted = Shifted(truth, [&](int c, double, double) {
    return std::make_pair(planted[c][0], planted[c][1]);
  });
  const ChannelShift shift = EstimateChannelShift(shifted, /*wrap=*/true);
  ASSERT_TRUE(shift.found);
  geometry::LinearImage whole = shifted, whole_map;
  CorrectChannelShift(whole, shift, &whole_map);
  for (const auto& [begin, end] : {std::pair{0, 1}, std::pair{37, 301}, std::pair{500, 512}}) {
    geometry::LinearImage part = shifted, part_map;
    const int64_t moved = CorrectChannelShift(part, shift, &part_map, begin, end);
    int64_t whole_moved = 0, differ = 0;
    for (int y = 0; y < h; ++y) {
      const geometry::LinearImage& expect = y >= begin && y < end ? whole : shifted;
      for (int x = 0; x < w; ++x) {
        const size_t p = size_t(y) * w + size_t(x);
        for (int c = 0; c < 3; ++c) differ += part.pixels[3 * p + c] != expect.pixels[3 * p + c];
        if (y >= begin && y < end) whole_moved += whole_map.pixels[p] < 1.0f;
      }
    }
    EXPECT_EQ(differ, 0) << "rows " << begin << ".." << end;
    EXPECT_EQ(moved, whole_moved) << "rows " << begin << ".." << end;
  }
}

// Claim (§9): a shift that grows across the image (red's dx from −1.5 px at the left edge to
// +1.5 px at the right, blue's dy from +1 px at the top to −1 px at the bottom) is followed by
// the tiles: each tile's offset is within 0.3 px of the planted one at its centre.
TEST(FringingTest, ShiftThatVariesOverTheImageIsFollowedByTheTiles) {
  const int w = 2048, h = 1024;
  const geometry::LinearImage truth = ThroughALens(MakePanorama(w, h, {}, false).image);
  auto planted = [&](int c, double x, double y) {
    return c == 0 ? std::make_pair(-1.5 + 3.0 * x / w, 0.0)
                  : std::make_pair(0.0, 1.0 - 2.0 * y / h);
  };
  const ChannelShift shift = EstimateChannelShift(Shifted(truth, planted), /*wrap=*/false);
  ASSERT_TRUE(shift.found);
  double worst = 0.0;
  for (int j = 0; j < shift.tiles_y; ++j) {
    for (int i = 0; i < shift.tiles_x; ++i) {
      const double x = (i + 0.5) * w / shift.tiles_x, y = (j + 0.5) * h / shift.tiles_y;
      const size_t t = size_t(j) * shift.tiles_x + size_t(i);
      for (int c = 0; c < 2; ++c) {
        const auto [dx, dy] = planted(c == 0 ? 0 : 2, x, y);
        worst = std::max({worst, std::abs(shift.tile_dx[t * 2 + size_t(c)] - dx),
                          std::abs(shift.tile_dy[t * 2 + size_t(c)] - dy)});
      }
    }
  }
  std::printf("varying fringing: %lld edge samples, largest offset %.2f px, worst tile off by "
              "%.3f px\n", (long long)shift.edges, shift.max_offset_px, worst);
  EXPECT_LE(worst, 0.3);
}

// Claim (§9): clean images (sharp textures, with or without a clipped surface) have no
// fringing: nothing is corrected and no pixel moves.
TEST(FringingTest, CleanImagesAreLeftUntouched) {
  for (const bool sheet : {false, true}) {
    geometry::LinearImage image = ThroughALens(MakePanorama(2048, 1024, {}, sheet).image);
    const geometry::LinearImage before = image;
    const ChannelShift shift = EstimateChannelShift(image, true);
    const int64_t moved = CorrectChannelShift(image, shift);
    std::printf("clean%s: %lld edge samples, largest offset %.3f px, %lld pixels moved\n",
                sheet ? " with a clipped sheet" : "", (long long)shift.edges,
                shift.max_offset_px, (long long)moved);
    EXPECT_FALSE(shift.found);
    EXPECT_EQ(moved, 0);
    EXPECT_EQ(image.pixels, before.pixels);
  }
}

}  // namespace
}  // namespace vasl::ingest

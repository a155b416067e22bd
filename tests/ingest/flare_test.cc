// VASL-MODEL §9, flare: bright sources planted with a known veiling glare on sharp textures;
// the detected map finds the pixels the glare affects (precision, recall), invalidates those it
// dominates, leaves clean images and sources without a veil at 1, and moves the colour a
// confidence-weighted blend gives toward the truth.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <vector>

#include <gtest/gtest.h>

#include "lattice/ingest/artefacts.h"
#include "tests/ingest/planted_panorama.h"

namespace vasl::ingest {
namespace {

/// Sources with a broad veil (a core of 30-60 px falling as d^−2 to d^−3, 0.15 to 0.5 of the
/// clip level at its centre) over the checkers, the stripes and the dark band; their bloom is
/// the saturation tests'.
std::vector<Source> FlaringSources() {
  std::vector<Source> s = {{300, 250, 6, 32.0, 3.0}, {1100, 700, 10, 64.0, 3.5},
                           {1700, 200, 4, 8.0, 2.5},  {700, 900, 5, 16.0, 3.0},
                           {20, 700, 6, 24.0, 3.0}};  // across the seam
  const double glare[5][3] = {{0.2, 40, 1.0}, {0.3, 60, 1.25}, {0.15, 30, 1.5}, {0.5, 50, 1.1},
                              {0.25, 45, 1.2}};
  for (size_t i = 0; i < s.size(); ++i) {
    s[i].glare = glare[i][0], s[i].glare_alpha_px = glare[i][1], s[i].glare_beta = glare[i][2];
  }
  return s;
}

/// True when planted glare adds more than `share` of pixel p's own light (not clipped).
bool Affected(const Planted& planted, size_t p, double share = 0.1) {
  for (int c = 0; c < 3; ++c) {
    if (planted.image.pixels[3 * p + c] >= 0.999f) return false;
  }
  return planted.glare[p] > share * planted.surface[p] && planted.glare[p] > 0.01;
}

// Claim (§9): around bright sources planted with a known veil, the pixels whose glare adds more
// than a tenth to their own light are found (precision and recall ≥ 0.9 over the pixels outside
// the clipped sources; glare within ±20% of that threshold is not scored). Invalidation errs on
// the side of keeping colour: under 1% of the invalid pixels have glare under 0.8× their own
// light, while at least 70% of those with glare over 1.2× it are invalid (the veil's tail
// beyond the rings measured is a fit's, a little steeper than the planted one).
TEST(FlareTest, FlareMapFindsPlantedGlare) {
  const int w = 2048, h = 1024;
  const Planted planted = MakePanorama(w, h, FlaringSources(), /*sheet=*/false);
  const FlareMap map = DetectFlare(planted.image, /*wrap=*/true);
  ASSERT_EQ(map.conf.pixels.size(), size_t(w) * h);
  int64_t truth = 0, found = 0, both = 0, dominated = 0, dominated_invalid = 0, wrongly_invalid = 0;
  for (size_t p = 0; p < map.conf.pixels.size(); ++p) {
    bool clipped = false;
    for (int c = 0; c < 3; ++c) clipped |= planted.image.pixels[3 * p + c] >= 0.999f;
    if (clipped) continue;
    // Glare within ±20% of the threshold is not scored: a veil falls so slowly that a wide
    // band of pixels lies at the threshold itself.
    const bool is = Affected(planted, p);
    if (is != Affected(planted, p, 0.1 / 1.2) || is != Affected(planted, p, 0.1 * 1.2)) continue;
    const bool said = map.conf.pixels[p] < 1.0f;
    truth += is;
    found += said;
    both += is && said;
    // Glare over the surface's own light plus its bloom: the surface is under half the pixel.
    const double own = planted.surface[p] + planted.bloom[p];
    if (planted.glare[p] > 1.2 * own) {
      ++dominated;
      dominated_invalid += map.conf.pixels[p] == 0.0f;
    }
    wrongly_invalid += map.conf.pixels[p] == 0.0f && planted.glare[p] < 0.8 * own;
  }
  const double precision = double(both) / double(std::max<int64_t>(1, found));
  const double recall = double(both) / double(std::max<int64_t>(1, truth));
  std::printf("flare: %d sources with a veil, %lld pixels planted / %lld found / %lld both: "
              "precision %.3f, recall %.3f; %lld invalid, %lld soft, farthest %d px; glare over "
              "1.2x the own light: %lld pixels, %lld invalid; invalid under 0.8x: %lld\n",
              map.sources, (long long)truth, (long long)found, (long long)both, precision, recall,
              (long long)map.invalid_pixels, (long long)map.soft_pixels, map.max_radius_px,
              (long long)dominated, (long long)dominated_invalid, (long long)wrongly_invalid);
  EXPECT_EQ(map.sources, int(FlaringSources().size()));
  EXPECT_GT(truth, 20000);
  EXPECT_GE(precision, 0.9);
  EXPECT_GE(recall, 0.9);
  EXPECT_GT(dominated, 5000);
  EXPECT_GE(dominated_invalid, int64_t(0.7 * double(dominated)));
  EXPECT_LE(wrongly_invalid, int64_t(0.01 * double(map.invalid_pixels)));
}

// Claim (§9): clean images, sharp textures with or without a clipped surface, and sources that
// bloom without a veil (the saturation tests' sources) keep the flare map at 1 on ≥ 99% of the
// pixels.
TEST(FlareTest, CleanImagesAndSourcesWithoutVeilStayAtOne) {
  struct Case {
    const char* name;
    Planted planted;
  };
  const Case cases[] = {{"clean", MakePanorama(1024, 512, {}, false)},
                        {"clipped sheet", MakePanorama(1024, 512, {}, true)},
                        {"bloom, no veil", MakePanorama(1024, 512, PlantedSources(), true)}};
  for (const Case& c : cases) {
    const FlareMap map = DetectFlare(c.planted.image, true);
    int64_t below = 0;
    for (float v : map.conf.pixels) below += v < 1.0f;
    const double at_one = 1.0 - double(below) / (1024.0 * 512.0);
    std::printf("%s: %d sources with a veil, %lld pixels below 1, %.3f%% at 1\n", c.name,
                map.sources, (long long)below, 100.0 * at_one);
    EXPECT_GE(at_one, 0.99) << c.name;
  }
}

// Claim (§7 with §9): blending a flared view with a clean view of the same surface, invalid
// pixels left out and the others weighted by conf^κ, moves the affected pixels' colour toward
// the surface's own: leaving the invalid pixels out lowers the mean error of the blend that
// ignores the map, κ = 1 lowers it further, and with κ = 2 it is under 0.7 of it.
TEST(FlareTest, ConfidenceWeightingMovesFlaredColourTowardTheTruth) {
  const Planted flared = MakePanorama(2048, 1024, FlaringSources(), false);
  const Planted clean = MakePanorama(2048, 1024, {}, false);
  const FlareMap map = DetectFlare(flared.image, true);
  double err[4] = {0.0, 0.0, 0.0, 0.0};  // ignored, κ = 0 (invalidation only), 1, 2
  int64_t pixels = 0;
  for (size_t p = 0; p < map.conf.pixels.size(); ++p) {
    if (!Affected(flared, p)) continue;
    const double conf = map.conf.pixels[p];
    const double w[4] = {1.0, conf > 0.0 ? 1.0 : 0.0, conf, conf * conf};
    for (int i = 0; i < 4; ++i) {
      for (int ch = 0; ch < 3; ++ch) {
        const double a = flared.image.pixels[3 * p + ch], truth = clean.image.pixels[3 * p + ch];
        err[i] += std::abs((w[i] * a + truth) / (w[i] + 1.0) - truth) / 3.0;
      }
    }
    ++pixels;
  }
  for (double& e : err) e /= double(std::max<int64_t>(1, pixels));
  std::printf("two-view blend over %lld flared pixels: mean |error| %.4f ignoring the map, "
              "%.4f with invalid pixels left out (kappa 0), %.4f with kappa 1, %.4f with kappa 2\n",
              (long long)pixels, err[0], err[1], err[2], err[3]);
  EXPECT_GT(pixels, 20000);
  EXPECT_LT(err[1], err[0]);
  EXPECT_LT(err[2], err[1]);
  EXPECT_LT(err[3], 0.7 * err[0]);
}

}  // namespace
}  // namespace vasl::ingest

// Claims of readout smear (VASL-MODEL §9): columns lifted uniformly through planted bright
// sources on sharp textures are found (precision and recall ≥ 0.9 over the pixels the smear adds
// more than a tenth of their light to), each source's lift measured within 0.02 of the clip
// level (the median over its columns; only the faintest, 0.1 on the checkers, may go unfound);
// the same sources without smear, and clean images, give no smeared column; the smear is a map
// (and a record's factor) of its own, apart from the bloom.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <vector>

#include <gtest/gtest.h>

#include "lattice/ingest/artefacts.h"
#include "tests/ingest/planted_panorama.h"

namespace vasl::ingest {
namespace {

constexpr int kW = 1024, kH = 512;
/// The smear of each PlantedSources() source, a fraction of the clip level.
const double kSmear[] = {0.1, 0.15, 0.3, 0.4, 0.12, 0.2};

/// Whether column x (pixel centre) lies within source s's disk's columns.
bool InColumns(const Source& s, int x) {
  const double dx = std::abs(x + 0.5 - s.cx);
  return std::min(dx, kW - dx) <= s.radius_px;
}

TEST(SmearTest, FindsPlantedColumnsAndNothingWithoutThem) {
  Planted planted = MakePanorama(kW, kH, PlantedSources(), /*sheet=*/false);
  const std::vector<Source> sources = PlantedSources();
  std::vector<float> smear(size_t(kW) * kH, 0.0f);
  for (int y = 0; y < kH; ++y) {
    for (int x = 0; x < kW; ++x) {
      const size_t p = size_t(y) * kW + x;
      for (size_t b = 0; b < sources.size(); ++b) {
        if (InColumns(sources[b], x)) smear[p] += float(kSmear[b]);
      }
      for (int c = 0; c < 3; ++c) {
        float& v = planted.image.pixels[3 * p + c];
        v = std::min(1.0f, v + smear[p]);
      }
    }
  }
  const SmearMap map = DetectSmear(planted.image, /*wrap=*/true);
  ASSERT_EQ(map.conf.pixels.size(), size_t(kW) * kH);
  int64_t truth = 0, found = 0, both = 0;
  for (size_t p = 0; p < smear.size(); ++p) {
    float level = 0.0f;
    for (int c = 0; c < 3; ++c) level = std::max(level, planted.image.pixels[3 * p + c]);
    if (level >= 0.999f) continue;  // clipped: saturation's
    const bool is = smear[p] > 0.1f * level;
    const bool said = map.conf.pixels[p] < 1.0f;
    truth += is;
    found += said;
    both += is && said;
  }
  const double precision = double(both) / double(std::max<int64_t>(1, found));
  const double recall = double(both) / double(std::max<int64_t>(1, truth));
  std::printf("smear: %d columns found (planted %d), largest lift %.3f (planted 0.4); %lld "
              "pixels planted / %lld found / %lld both: precision %.3f, recall %.3f\n",
              map.columns, [&] {
                int n = 0;
                for (int x = 0; x < kW; ++x) {
                  for (const Source& s : sources) n += InColumns(s, x);
                }
                return n;
              }(), map.max_offset, (long long)truth, (long long)found, (long long)both,
              precision, recall);
  EXPECT_GT(truth, 5000);
  EXPECT_GE(precision, 0.9);
  EXPECT_GE(recall, 0.9);
  // Each source's smear: the median over its columns found.
  for (size_t b = 0; b < sources.size(); ++b) {
    std::vector<float> found_s;
    for (int x = 0; x < kW; ++x) {
      if (InColumns(sources[b], x) && map.column_offset[size_t(x)] > 0.0f) {
        found_s.push_back(map.column_offset[size_t(x)]);
      }
    }
    if (found_s.empty()) {
      // The faintest (0.1 over checkers of ±0.16, 90 rows above it) may go unfound: four
      // standard errors of the texture's own lift are more than it.
      std::printf("source %zu: planted smear %.2f, not found\n", b, kSmear[b]);
      EXPECT_LE(kSmear[b], 0.1) << "source " << b;
      continue;
    }
    std::nth_element(found_s.begin(), found_s.begin() + found_s.size() / 2, found_s.end());
    std::printf("source %zu: planted smear %.2f, found on %zu columns, median %.3f\n", b,
                kSmear[b], found_s.size(), found_s[found_s.size() / 2]);
    EXPECT_NEAR(found_s[found_s.size() / 2], kSmear[b], 0.02);
  }
  // Every map of the image keeps it apart (conf[smear]): the saturation map holds the bloom
  // alone, and leaves most smeared pixels at 1.
  const ArtefactMaps all = DetectArtefacts(planted.image, true);
  EXPECT_EQ(all.smear.conf.pixels, map.conf.pixels);
  int64_t apart = 0;
  for (size_t p = 0; p < smear.size(); ++p) {
    apart += map.conf.pixels[p] < 1.0f && all.saturation.conf.pixels[p] == 1.0f;
  }
  std::printf("%lld of the %lld smeared pixels at 1 in the saturation map\n", (long long)apart,
              (long long)map.soft_pixels);
  EXPECT_GE(apart, map.soft_pixels / 2);

  const Planted unsmeared = MakePanorama(kW, kH, PlantedSources(), /*sheet=*/true);
  const SmearMap none = DetectSmear(unsmeared.image, true);
  std::printf("the same sources without smear: %d columns; a clean image: %d\n", none.columns,
              DetectSmear(MakePanorama(kW, kH, {}, false).image, true).columns);
  EXPECT_EQ(none.columns, 0);
  EXPECT_TRUE(none.conf.pixels.empty());
  EXPECT_TRUE(DetectSmear(MakePanorama(kW, kH, {}, false).image, true).conf.pixels.empty());
}

}  // namespace
}  // namespace vasl::ingest

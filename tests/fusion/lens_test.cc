// Claims of the §9 lens map as fusion applies it: a record seen through dirt D and veil v
// with exposure g, C_obs = g·(D·C + v), is corrected to g·C exactly and its conf[dirt] takes
// D·(1 − g·v/C_obs); a profile that lists maps it has not loaded is refused; maps and profiles
// read back from their catalog text bit for bit.
#include <cmath>

#include <gtest/gtest.h>

#include "lattice/fusion/fuse.h"
#include "lattice/fusion/lens.h"

namespace vasl::fusion {
namespace {

/// A 4×2-cell map over a 40×20 image: dirt 0.5 on the left half, veil 0.1 on the right.
LensMap HalfAndHalf() {
  LensMap m;
  m.rig = "rig a";
  m.camera = "pano";
  m.period = "3 frames";
  m.image_w = 40;
  m.image_h = 20;
  m.grid_w = 4;
  m.grid_h = 2;
  m.transmission.assign(4 * 2 * 3, 1.0f);
  m.veil.assign(4 * 2 * 3, 0.0f);
  for (int y = 0; y < 2; ++y) {
    for (int x = 0; x < 4; ++x) {
      for (int c = 0; c < 3; ++c) {
        const size_t i = (size_t(y) * 4 + x) * 3 + c;
        if (x < 2) m.transmission[i] = 0.5f;
        else m.veil[i] = 0.1f;
      }
    }
  }
  m.source_gain[7] = {0.9f, 1.0f, 1.1f};
  return m;
}

TEST(LensTest, CorrectsDirtAndVeilAndLowersTheConfidence) {
  const LensMap m = HalfAndHalf();
  const std::array<float, 3> g = m.source_gain.at(7);
  const float scene[3] = {0.2f, 0.4f, 0.6f};
  // In a cell centre on the dirty side (cell 0: centre at u = 5, v = 5).
  float value[3], uv[2] = {5.0f, 5.0f};
  for (int c = 0; c < 3; ++c) value[c] = g[c] * 0.5f * scene[c];
  LensFactors conf = AdjustForLens(m, g, uv, value);
  for (int c = 0; c < 3; ++c) EXPECT_NEAR(value[c], g[c] * scene[c], 1e-6f);
  EXPECT_FLOAT_EQ(conf.dirt, 0.5f);
  EXPECT_FLOAT_EQ(conf.fog, 1.0f);
  // On the veiled side: the darkest channel's share of scene light sets the fog factor.
  uv[0] = 35.0f;
  for (int c = 0; c < 3; ++c) value[c] = g[c] * (scene[c] + 0.1f);
  conf = AdjustForLens(m, g, uv, value);
  for (int c = 0; c < 3; ++c) EXPECT_NEAR(value[c], g[c] * scene[c], 1e-6f);
  EXPECT_FLOAT_EQ(conf.dirt, 1.0f);
  EXPECT_NEAR(conf.fog, 0.2f / 0.3f, 1e-6f);
  // Between the halves (u = 20, midway from the centre at 15 to the one at 25): D and v blend.
  float d[3], v[3];
  m.Sample(20.0f, 5.0f, d, v);
  EXPECT_FLOAT_EQ(d[0], 0.75f);
  EXPECT_FLOAT_EQ(v[0], 0.05f);
  EXPECT_DOUBLE_EQ(m.DirtShare(), 0.5);
  EXPECT_DOUBLE_EQ(m.VeilShare(), 0.5);
}

TEST(LensTest, FusionAppliesTheMapOnlyToItsSourcesAndOnlyWhenLoaded) {
  // One vossel, two records: source 7 through the dirty half, source 8 clean, same scene.
  records::RecordSet recs;
  recs.Resize(2);
  for (size_t i = 0; i < 2; ++i) {
    recs.vossel[i] = 0;
    recs.scan[i] = int32_t(7 + i);
    recs.modality[i] = int8_t(records::Modality::kRgb);
    recs.range_m[i] = 2.0f;
    recs.cos_inc[i] = 1.0f;
    recs.foot_major_m[i] = recs.foot_minor_m[i] = 0.005f;
    recs.vis[i] = 1.0f;
    for (int f = 0; f < records::kConfidenceCount; ++f) {
      recs.conf[i * records::kConfidenceCount + f] = 1.0f;
    }
    recs.flags[i] = 0;
    recs.batch[i] = 1;
    recs.uv_px[2 * i] = 5.0f;
    recs.uv_px[2 * i + 1] = 5.0f;
  }
  LensMap m = HalfAndHalf();
  m.source_gain[7] = {1.0f, 1.0f, 1.0f};
  for (int c = 0; c < 3; ++c) {
    recs.value[c] = 0.5f * 0.4f;  // source 7: dirt halves it
    recs.value[3 + c] = 0.4f;     // source 8: the scene
  }
  WeightingProfile plain;
  auto ignoring = Fuse(recs, 1, 0.02, plain);
  ASSERT_TRUE(ignoring.ok()) << ignoring.status();
  EXPECT_NEAR(ignoring->by_modality.at(records::Modality::kRgb).value[0], 0.3f, 1e-6f);

  WeightingProfile lens = plain;
  lens.name = "lens";
  lens.lens_maps = {1};
  auto unloaded = Fuse(recs, 1, 0.02, lens);
  EXPECT_EQ(unloaded.status().code(), absl::StatusCode::kFailedPrecondition);
  lens.lens = LensTable::Of({std::make_shared<const LensMap>(m)});
  auto applying = Fuse(recs, 1, 0.02, lens);
  ASSERT_TRUE(applying.ok()) << applying.status();
  EXPECT_NEAR(applying->by_modality.at(records::Modality::kRgb).value[0], 0.4f, 1e-6f);
  // conf[dirt] of source 7 is 0.5 (κ = 1): the weights are 0.5 and 1.
  auto w = RecordWeights(recs, 1, 0.02, lens);
  ASSERT_TRUE(w.ok());
  EXPECT_NEAR(w->weight[0] / w->weight[1], 0.5f, 1e-6f);
  lens.kappa[records::kConfDirt] = 0.0;  // κ_dirt = 0: corrected, not down-weighted
  w = RecordWeights(recs, 1, 0.02, lens);
  ASSERT_TRUE(w.ok());
  EXPECT_FLOAT_EQ(w->weight[0], w->weight[1]);
  // Source 7 seen through the veil instead (v = 0.1 over 0.4): corrected to the scene, and its
  // conf[fog] is the scene's share, 0.8, which κ_fog weighs apart from κ_dirt.
  recs.uv_px[0] = 35.0f;
  for (int c = 0; c < 3; ++c) recs.value[c] = 0.4f + 0.1f;
  applying = Fuse(recs, 1, 0.02, lens);
  ASSERT_TRUE(applying.ok()) << applying.status();
  EXPECT_NEAR(applying->by_modality.at(records::Modality::kRgb).value[0], 0.4f, 1e-6f);
  w = RecordWeights(recs, 1, 0.02, lens);
  ASSERT_TRUE(w.ok());
  EXPECT_NEAR(w->weight[0] / w->weight[1], 0.8f, 1e-6f);
  lens.kappa[records::kConfFog] = 0.0;
  w = RecordWeights(recs, 1, 0.02, lens);
  ASSERT_TRUE(w.ok());
  EXPECT_FLOAT_EQ(w->weight[0], w->weight[1]);
}

TEST(LensTest, MapsAndProfilesReadBackFromTheirTextBitForBit) {
  LensMap m = HalfAndHalf();
  m.transmission[5] = 0.123456789f;
  m.veil[20] = 1.0f / 3.0f;
  auto back = LensMapFromText(LensMapToText(m));
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->rig, m.rig);
  EXPECT_EQ(back->camera, m.camera);
  EXPECT_EQ(back->period, m.period);
  EXPECT_EQ(back->transmission, m.transmission);
  EXPECT_EQ(back->veil, m.veil);
  EXPECT_EQ(back->source_gain, m.source_gain);
  std::string cut = LensMapToText(m);  // its last cell's veil lost
  cut.resize(cut.rfind(' '));
  EXPECT_EQ(LensMapFromText(cut).status().code(), absl::StatusCode::kDataLoss);

  WeightingProfile p;
  p.name = "lens";
  p.lens_maps = {3, 12};
  auto q = ProfileFromText(ProfileToText(p));
  ASSERT_TRUE(q.ok()) << q.status();
  EXPECT_EQ(q->lens_maps, p.lens_maps);
  p.lens_maps = {0};
  EXPECT_EQ(ValidateProfile(p).code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace vasl::fusion

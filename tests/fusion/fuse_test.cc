// VASL-MODEL §7: weights, fusion, reweighting from records alone.
#include "lattice/fusion/fuse.h"

#include <random>

#include <gtest/gtest.h>

#include "lattice/fusion/weight.h"

namespace vasl::fusion {
namespace {

using records::Modality;

// One RGB record with the given attributes.
void AddRecord(records::RecordSet& s, int32_t vossel, int32_t scan, float value, float vis,
               float cos_inc, float foot_m, bool derived = false) {
  const size_t i = s.size();
  s.Resize(i + 1);
  s.vossel[i] = vossel;
  s.scan[i] = scan;
  s.modality[i] = int8_t(derived ? Modality::kDerived : Modality::kRgb);
  for (int c = 0; c < 3; ++c) s.value[i * 3 + c] = value;
  s.range_m[i] = 3.0f;
  s.cos_inc[i] = cos_inc;
  s.foot_major_m[i] = foot_m;
  s.foot_minor_m[i] = foot_m;
  s.vis[i] = vis;
  for (int f = 0; f < records::kConfidenceCount; ++f) {
    s.conf[i * records::kConfidenceCount + f] = 1.0f;
  }
  s.flags[i] = derived ? records::kFlagDerived : 0;
  s.batch[i] = 1;
}

// Claim (§7): each factor of w acts as written; V below V_min gives 0; K_range discounts
// footprints wider than s* = h/2 (§4.2).
TEST(WeightTest, FactorsOfTheWeight) {
  WeightingProfile p;
  const float conf[records::kConfidenceCount] = {1, 1, 1, 1, 1, 1};
  WeightInputs in{1.0f, 0.5f, 0.005f, 0.005f, conf, 3, false, 2.0f, 2.0f};
  const double h = 0.02, target = h / 2;
  EXPECT_DOUBLE_EQ(RecordWeight(p, in, target, 1.0), 0.5);  // cosθ^1, K_range = 1
  in.vis = 0.49f;
  EXPECT_EQ(RecordWeight(p, in, target, 1.0), 0.0);  // below V_min = 0.5
  in.vis = 0.8f;
  p.beta = 2.0;
  EXPECT_NEAR(RecordWeight(p, in, target, 1.0), 0.64 * 0.5, 1e-7);
  in.vis = 1.0f;
  in.foot_major_m = 0.04f;  // 4 s*: K_range = 1/4
  EXPECT_NEAR(RecordWeight(p, in, target, 1.0), 0.5 * 0.25, 1e-7);
  p.rho = 0.0;
  EXPECT_NEAR(RecordWeight(p, in, target, 1.0), 0.5, 1e-7);
  in.derived = true;
  EXPECT_NEAR(RecordWeight(p, in, target, 2.0), 0.5 * 0.5 * 2.0, 1e-7);  // λ_src, g_m
  const float low_conf[records::kConfidenceCount] = {0.5f, 1, 1, 1, 1, 1};
  in.conf = low_conf;
  in.derived = false;
  EXPECT_NEAR(RecordWeight(p, in, target, 1.0), 0.25, 1e-7);
}

// Claim (§7): C_k is the weighted mean of its records; U_k = spread ⊕ 1/sqrt(Σw);
// reweighting reads records only and changes the result as the new profile says.
TEST(FuseTest, WeightedMeanUncertaintyAndReweight) {
  records::RecordSet s;
  AddRecord(s, 0, 1, 0.2f, 1.0f, 1.0f, 0.001f);
  AddRecord(s, 0, 2, 0.8f, 1.0f, 0.25f, 0.001f);
  AddRecord(s, 1, 1, 0.4f, 0.3f, 1.0f, 0.001f);  // below V_min: no weight
  AddRecord(s, 2, 1, 0.6f, 1.0f, 1.0f, 0.001f);
  AddRecord(s, 2, 2, 0.1f, 1.0f, 1.0f, 0.001f, /*derived=*/true);
  WeightingProfile p;
  auto fused = Fuse(s, 3, 0.02, p);
  ASSERT_TRUE(fused.ok()) << fused.status();
  const auto& rgb = fused->by_modality.at(Modality::kRgb);
  const double mean0 = (0.2 * 1.0 + 0.8 * 0.25) / 1.25;
  EXPECT_NEAR(rgb.value[0], mean0, 1e-6);
  EXPECT_NEAR(rgb.weight[0], 1.25, 1e-6);
  const double var0 = (1.0 * std::pow(0.2 - mean0, 2) + 0.25 * std::pow(0.8 - mean0, 2)) / 1.25;
  EXPECT_NEAR(rgb.uncertainty[0], std::sqrt(var0 + 1.0 / 1.25), 1e-6);
  EXPECT_EQ(rgb.weight[1], 0.0f);
  EXPECT_NEAR(rgb.value[2 * 3], (0.6 + 0.5 * 0.1) / 1.5, 1e-6);  // derived at λ_src = 0.5

  // Reweight: α = 0 makes incidence irrelevant; λ_src = 0 excludes derived records.
  p.alpha = 0.0;
  p.lambda_src = 0.0;
  p.v_min = 0.25;
  auto re = Fuse(s, 3, 0.02, p);
  ASSERT_TRUE(re.ok());
  const auto& rgb2 = re->by_modality.at(Modality::kRgb);
  EXPECT_NEAR(rgb2.value[0], 0.5, 1e-6);
  EXPECT_NEAR(rgb2.value[3], 0.4, 1e-6);  // V = 0.3 ≥ new V_min, β = 1
  EXPECT_NEAR(rgb2.weight[1], 0.3, 1e-6);
  EXPECT_NEAR(rgb2.value[6], 0.6, 1e-6);

  p.mode = FusionMode::kNearest;
  p.alpha = 1.0;
  auto nearest = Fuse(s, 3, 0.02, p);
  ASSERT_TRUE(nearest.ok());
  EXPECT_NEAR(nearest->by_modality.at(Modality::kRgb).value[0], 0.2, 1e-6);
}

// Claim (§7): fusing noisy records of one true colour recovers it, and U shrinks as records
// accumulate (1/sqrt(Σw) term); a bad profile is rejected.
TEST(FuseTest, ConvergesAndValidates) {
  std::mt19937 rng(3);
  std::normal_distribution<float> noise(0.0f, 0.02f);
  records::RecordSet s;
  const int vossels = 2000;
  for (int k = 0; k < vossels; ++k) {
    const int n = 1 + k % 8;
    for (int m = 0; m < n; ++m) AddRecord(s, k, m, 0.5f + noise(rng), 1.0f, 1.0f, 0.001f);
  }
  auto fused = Fuse(s, vossels, 0.02, WeightingProfile{});
  ASSERT_TRUE(fused.ok());
  const auto& rgb = fused->by_modality.at(Modality::kRgb);
  double err8 = 0.0;
  int n8 = 0;
  for (int k = 7; k < vossels; k += 8, ++n8) err8 += std::abs(rgb.value[k * 3] - 0.5);
  std::printf("fused |C-0.5| mean over vossels with 8 records: %.4f (record noise σ 0.02)\n",
              err8 / n8);
  EXPECT_LT(err8 / n8, 0.02 / std::sqrt(8.0) * 1.5);
  EXPECT_GT(rgb.uncertainty[0], rgb.uncertainty[7]);
  WeightingProfile bad;
  bad.v_min = 1.5;
  EXPECT_EQ(Fuse(s, vossels, 0.02, bad).status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace vasl::fusion

// VASL-MODEL §7: what each profile parameter does to the fused colour, on two synthetic scans
// of known, different colour that see the same vossels (scan 1 head-on and near, scan 2 at a
// grazing angle and far): α, θ_max, `nearest` and the proximity term; and the profile's text
// form reads back bit for bit.
#include <cmath>
#include <cstdio>

#include <gtest/gtest.h>

#include "lattice/fusion/fuse.h"
#include "lattice/geometry/footprint.h"

namespace vasl::fusion {
namespace {

using records::Modality;

constexpr double kH = 0.02;
constexpr size_t kVossels = 500;
// Scan 1 (source 1): head-on (cosθ 0.95), 3 m, reddish. Scan 2 (source 2): grazing (cosθ 0.2,
// θ = 78.5°), 6 m, bluish. Footprints below s* = h/2, so K_range = 1 for both.
constexpr float kCos1 = 0.95f, kCos2 = 0.2f, kRange1 = 3.0f, kRange2 = 6.0f;
const float kColour1[3] = {0.8f, 0.3f, 0.2f}, kColour2[3] = {0.2f, 0.3f, 0.8f};

records::RecordSet TwoScans() {
  records::RecordSet s;
  for (size_t k = 0; k < kVossels; ++k) {
    for (int m = 0; m < 2; ++m) {
      const size_t i = s.size();
      s.Resize(i + 1);
      s.vossel[i] = int32_t(k);
      s.scan[i] = m + 1;
      s.modality[i] = int8_t(Modality::kRgb);
      // A per-vossel texture on top of the scan's colour, identical in both scans' ratio.
      const float texture = 0.8f + 0.4f * float(k % 7) / 6.0f;
      for (int c = 0; c < 3; ++c) s.value[i * 3 + c] = texture * (m == 0 ? kColour1[c] : kColour2[c]);
      s.range_m[i] = m == 0 ? kRange1 : kRange2;
      s.cos_inc[i] = m == 0 ? kCos1 : kCos2;
      s.foot_major_m[i] = 0.004f;
      s.foot_minor_m[i] = 0.004f;
      s.vis[i] = 1.0f;
      for (int f = 0; f < records::kConfidenceCount; ++f) {
        s.conf[i * records::kConfidenceCount + f] = 1.0f;
      }
      s.flags[i] = 0;
      s.batch[i] = m + 1;
    }
  }
  return s;
}

/// Largest |C_k − expected_k| over vossels and channels, with expected = a·C1 + (1 − a)·C2
/// where a is the share of scan 1's weight.
double WorstError(const records::FusedValues& f, const records::RecordSet& s, double share1) {
  const auto& rgb = f.by_modality.at(Modality::kRgb);
  double worst = 0.0;
  for (size_t k = 0; k < kVossels; ++k) {
    for (int c = 0; c < 3; ++c) {
      const double expected = share1 * s.value[(2 * k) * 3 + c] + (1.0 - share1) * s.value[(2 * k + 1) * 3 + c];
      worst = std::max(worst, std::abs(double(rgb.value[k * 3 + c]) - expected));
    }
  }
  return worst;
}

// Claim: with α the weights are cos^α, so scan 1's share is 0.95^α / (0.95^α + 0.2^α): 0.826
// at α = 1, 1 − 2e-6 at α = 8; a high α lets the head-on scan's colour win.
TEST(ProfileClaimsTest, HighAlphaLetsTheHeadOnScanWin) {
  const records::RecordSet s = TwoScans();
  for (double alpha : {1.0, 2.0, 8.0}) {
    WeightingProfile p;
    p.alpha = alpha;
    auto f = Fuse(s, kVossels, kH, p);
    ASSERT_TRUE(f.ok()) << f.status();
    const double w1 = std::pow(kCos1, alpha), w2 = std::pow(kCos2, alpha);
    const double share = w1 / (w1 + w2);
    const double err = WorstError(*f, s, share);
    const double to_head_on = WorstError(*f, s, 1.0);
    std::printf("alpha %.0f: scan 1's share %.6f, fused within %.2g of it, %.3g from scan 1's colour\n",
                alpha, share, err, to_head_on);
    EXPECT_LT(err, 1e-6);
    if (alpha == 8.0) EXPECT_LT(to_head_on, 1e-5);
  }
}

// Claim: θ_max drops the grazing scan (78.5° > 70°): the fused colour is scan 1's exactly.
TEST(ProfileClaimsTest, ThetaMaxDropsTheGrazingScan) {
  const records::RecordSet s = TwoScans();
  WeightingProfile p;
  p.theta_max_rad = 70.0 * M_PI / 180.0;
  auto f = Fuse(s, kVossels, kH, p);
  ASSERT_TRUE(f.ok());
  EXPECT_EQ(WorstError(*f, s, 1.0), 0.0);
  p.theta_max_rad = 80.0 * M_PI / 180.0;  // both within: a blend again
  f = Fuse(s, kVossels, kH, p);
  EXPECT_GT(WorstError(*f, s, 1.0), 0.01);
}

// Claim: the proximity term multiplies each weight by exp(−(r − r_min)/ρ_p): scan 2, 3 m
// farther, counts exp(−3/ρ_p) times less than with ρ_p off; `nearest` mode takes the record
// of greatest weight alone, here the nearer scan's, exactly.
TEST(ProfileClaimsTest, ProximityAndNearestPreferTheNearerScan) {
  const records::RecordSet s = TwoScans();
  WeightingProfile p;
  p.alpha = 0.0;  // equal weights but for proximity
  for (double rho_p : {0.0, 1.0, 3.0}) {
    p.proximity_m = rho_p;
    auto f = Fuse(s, kVossels, kH, p);
    ASSERT_TRUE(f.ok());
    const double factor = rho_p > 0.0 ? std::exp(-(kRange2 - kRange1) / rho_p) : 1.0;
    const double share = 1.0 / (1.0 + factor);
    const double err = WorstError(*f, s, share);
    std::printf("proximity rho_p %.0f m: farther scan's weight x %.4f, scan 1's share %.4f, "
                "fused within %.2g\n", rho_p, factor, share, err);
    EXPECT_LT(err, 1e-6);
  }
  p.proximity_m = 1.0;
  p.mode = FusionMode::kNearest;
  auto f = Fuse(s, kVossels, kH, p);
  ASSERT_TRUE(f.ok());
  EXPECT_EQ(WorstError(*f, s, 1.0), 0.0) << "nearest mode must take the nearer scan's record";
  p.proximity_m = 0.0;
  p.alpha = 0.0;
  p.scan_gain[1] = 0.5;  // scan 1's weight halved: the other scan is now the greatest
  f = Fuse(s, kVossels, kH, p);
  EXPECT_EQ(WorstError(*f, s, 0.0), 0.0);
}

// Claim: a profile's text form (what the catalog keeps) reads back bit for bit.
TEST(ProfileClaimsTest, TextFormRoundTrips) {
  WeightingProfile p;
  p.name = "site-2027.v2";
  p.version = 7;
  p.alpha = 1.0 / 3.0;
  p.beta = 0.1;
  p.rho = 2.5;
  p.kappa = {0.3, 1.0, 2.0, 0.0};
  p.v_min = 1.0 / 17.0;
  p.lambda_src = 0.25;
  p.theta_max_rad = 1.2345678901234567;
  p.proximity_m = 1e-3;
  p.mode = FusionMode::kNearest;
  p.scan_gain = {{3, 0.5}, {11, 1.0 / 7.0}};
  p.channel_gain = {{2, {1.1, 0.9, 1.0 / 3.0}}};
  auto back = ProfileFromText(ProfileToText(p));
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(ProfileToText(*back), ProfileToText(p));
  EXPECT_EQ(back->alpha, p.alpha);
  EXPECT_EQ(back->theta_max_rad, p.theta_max_rad);
  EXPECT_EQ(back->scan_gain, p.scan_gain);
  EXPECT_EQ(back->channel_gain, p.channel_gain);
  EXPECT_EQ(back->mode, FusionMode::kNearest);
  EXPECT_EQ(ProfileFromText("alpha two\n").status().code(), absl::StatusCode::kDataLoss);
  EXPECT_EQ(ProfileFromText("unknown 1\n").status().code(), absl::StatusCode::kDataLoss);
}

}  // namespace
}  // namespace vasl::fusion

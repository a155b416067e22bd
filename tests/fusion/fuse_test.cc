// VASL-MODEL §7: weights, fusion, reweighting from records alone.
#include "lattice/fusion/fuse.h"

#include <array>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <random>
#include <vector>

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
  EXPECT_DOUBLE_EQ(RecordWeight(p, in, target), 0.5);  // cosθ^1, K_range = 1
  in.vis = 0.49f;
  EXPECT_EQ(RecordWeight(p, in, target), 0.0);  // below V_min = 0.5
  in.vis = 0.8f;
  p.beta = 2.0;
  EXPECT_NEAR(RecordWeight(p, in, target), 0.64 * 0.5, 1e-7);
  in.vis = 1.0f;
  in.foot_major_m = 0.04f;  // 4 s*: K_range = 1/4
  EXPECT_NEAR(RecordWeight(p, in, target), 0.5 * 0.25, 1e-7);
  p.rho = 0.0;
  EXPECT_NEAR(RecordWeight(p, in, target), 0.5, 1e-7);
  in.derived = true;
  p.scan_gain[3] = 2.0;
  EXPECT_NEAR(RecordWeight(p, in, target), 0.5 * 0.5 * 2.0, 1e-7);  // λ_src, g_m
  p.scan_gain.clear();
  const float low_conf[records::kConfidenceCount] = {0.5f, 1, 1, 1, 1, 1};
  in.conf = low_conf;
  in.derived = false;
  EXPECT_NEAR(RecordWeight(p, in, target), 0.25, 1e-7);
}

/// §7 in double precision with std::pow, the formula as VASL-MODEL writes it: the reference
/// the float kernel is held to.
double ReferenceWeight(const WeightingProfile& p, const records::RecordSet& r, size_t i,
                       double target_m, double range_min_m) {
  if (r.vis[i] < p.v_min || r.vis[i] <= 0.0f || (r.flags[i] & records::kFlagInvalidated)) {
    return 0.0;
  }
  const double cos_inc = std::max(0.0, double(r.cos_inc[i]));
  if (p.theta_max_rad > 0.0 && cos_inc < std::cos(p.theta_max_rad)) return 0.0;
  const auto pow = [](double x, double e) { return e == 0.0 ? 1.0 : std::pow(x, e); };
  const double k = std::min(1.0, target_m / r.foot_major_m[i]) *
                   std::min(1.0, target_m / r.foot_minor_m[i]);
  double w = pow(r.vis[i], p.beta) * pow(cos_inc, p.alpha) * pow(k, p.rho);
  for (int f = 0; f < records::kConfidenceCount; ++f) {
    w *= pow(r.conf[i * records::kConfidenceCount + f], p.kappa[f]);
  }
  if (r.flags[i] & records::kFlagDerived) w *= p.lambda_src;
  const auto g = p.scan_gain.find(r.scan[i]);
  if (g != p.scan_gain.end()) w *= g->second;
  if (p.proximity_m > 0.0) w *= std::exp(-(r.range_m[i] - range_min_m) / p.proximity_m);
  return w;
}

// n records of random attributes: invalidated and derived ones, negative cosines, zero and
// unit confidences among them.
records::RecordSet RandomRecords(size_t n, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(0.0f, 1.0f);
  records::RecordSet r;
  r.Resize(n);
  for (size_t i = 0; i < n; ++i) {
    r.vossel[i] = int32_t(i);
    r.scan[i] = int32_t(1 + i % 5);
    r.modality[i] = int8_t(Modality::kRgb);
    r.range_m[i] = 0.5f + 30.0f * u(rng);
    r.cos_inc[i] = i % 17 == 0 ? -0.2f : u(rng);
    r.foot_major_m[i] = 0.03f * u(rng) + 1e-4f;
    r.foot_minor_m[i] = r.foot_major_m[i] * (0.3f + 0.7f * u(rng));
    r.vis[i] = i % 7 == 0 ? 1.0f : u(rng);
    for (int f = 0; f < records::kConfidenceCount; ++f) {
      const float x = u(rng);
      r.conf[i * records::kConfidenceCount + f] = x < 0.02f ? 0.0f : x < 0.5f ? 1.0f : x;
    }
    r.flags[i] = int8_t(i % 11 == 0   ? records::kFlagDerived
                        : i % 13 == 0 ? records::kFlagInvalidated
                                      : 0);
  }
  return r;
}

// A general profile (exponents through logarithms, gates, gains, proximity) and one of
// exponents 0, 1 and 2 alone (every factor multiplies).
WeightingProfile GeneralProfile() {
  WeightingProfile general;
  general.alpha = 1.3;
  general.beta = 0.7;
  general.rho = 0.5;
  general.kappa = {2.5, 0.0, 0.5, 1.2, 2.0, 1.7};  // κ = 0 on flare: conf 0 there leaves w alone
  general.v_min = 0.2;
  general.theta_max_rad = 1.4;
  general.proximity_m = 4.0;
  general.scan_gain = {{2, 0.5}, {4, 3.0}};
  return general;
}
WeightingProfile ProductsProfile() {
  WeightingProfile products;
  products.beta = 2.0;
  products.kappa = {1.0, 0.0, 2.0, 1.0, 1.0, 0.0};
  return products;
}

// Claim (§7, the weight kernel): one exp of a sum of logs gives the weight of std::pow to a
// relative 2·10⁻⁶ under general exponents (and 10⁻⁶ when every exponent is 0, 1 or 2), a zero
// factor under a positive exponent gives exactly 0, a zero exponent leaves the factor out even
// where it is 0, and a record's weight does not depend on the run it is evaluated in.
TEST(WeightTest, KernelMatchesTheFormulaInDouble) {
  const size_t n = 1003;  // not a multiple of the kernel's runs of 4 and 256 records
  const records::RecordSet r = RandomRecords(n, 11);
  const double target = 0.01;
  for (const auto& [p, tolerance] :
       {std::pair{GeneralProfile(), 2e-6}, std::pair{ProductsProfile(), 1e-6}}) {
    const WeightKernel kernel(p, target);
    std::vector<float> range_min(n, 0.5f), whole(n), one(n);
    WeightColumns c = WeightColumns::Of(r);
    c.range_min_m = range_min.data();
    kernel.Evaluate(c, n, whole.data());
    double worst = 0.0;
    int zeros = 0;
    for (size_t i = 0; i < n; ++i) {
      WeightColumns ci = WeightColumns::Of(r, i);
      ci.range_min_m = &range_min[i];
      kernel.Evaluate(ci, 1, &one[i]);
      EXPECT_EQ(one[i], whole[i]) << "record " << i;  // bit for bit, alone or in a run
      const double expect = ReferenceWeight(p, r, i, target, range_min[i]);
      if (expect == 0.0) {
        EXPECT_EQ(whole[i], 0.0f) << "record " << i;
        ++zeros;
        continue;
      }
      worst = std::max(worst, std::abs(whole[i] / expect - 1.0));
    }
    std::printf("weight kernel: %zu records, %d exact zeros, worst relative error %.2g\n", n,
                zeros, worst);
    EXPECT_LT(worst, tolerance);
    EXPECT_GT(zeros, 50);              // gates and zero factors were exercised
    EXPECT_GT(int(n) - zeros, 300);    // and enough weights to hold the tolerance to
  }
}

// Claim (§7, weights that do not depend on the machine): every instruction set's variant of
// the kernel this CPU runs (baseline SSE2, AVX2, x86-64-v4's AVX-512) gives the same bits for
// every record, so that a project reweighted or rebuilt on another machine fuses alike.
TEST(WeightTest, EveryInstructionSetGivesTheSameBits) {
  const size_t n = 100003;
  const records::RecordSet r = RandomRecords(n, 23);
  std::vector<float> range_min(n);
  for (size_t i = 0; i < n; ++i) range_min[i] = r.range_m[i] * (i % 3 == 0 ? 1.0f : 0.8f);
  WeightColumns c = WeightColumns::Of(r);
  c.range_min_m = range_min.data();
  using Isa = WeightKernel::Isa;
  int compared = 0;
  for (const WeightingProfile& p : {GeneralProfile(), ProductsProfile()}) {
    const WeightKernel kernel(p, 0.01);
    std::vector<float> baseline(n), other(n);
    kernel.EvaluateOn(Isa::kBaseline, c, n, baseline.data());
    for (Isa isa : {Isa::kAvx2, Isa::kX86_64_V4}) {
      if (!memory::Supports(isa)) continue;
      kernel.EvaluateOn(isa, c, n, other.data());
      size_t differ = 0;
      for (size_t i = 0; i < n; ++i) differ += std::memcmp(&other[i], &baseline[i], 4) != 0;
      EXPECT_EQ(differ, 0u) << "instruction set " << int(isa);
      ++compared;
    }
    std::vector<float> chosen(n);
    kernel.Evaluate(c, n, chosen.data());
    EXPECT_EQ(std::memcmp(chosen.data(), baseline.data(), n * sizeof(float)), 0);
  }
  std::printf("weight kernel: %d variants beside the baseline compared bit for bit over %zu "
              "records\n", compared, n);
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

// Claim (§7): a record whose weight is 0 (here: V below V_min, and a hard invalidation) takes
// no part in its vossel's fusion, whatever its value holds: NaN or ∞ leave the vossel's value,
// weight and uncertainty exactly as the other records alone give them, in both modes.
TEST(FuseTest, RecordsWithoutWeightLeaveNoTrace) {
  records::RecordSet clean;
  AddRecord(clean, 0, 1, 0.2f, 1.0f, 1.0f, 0.001f);
  AddRecord(clean, 0, 2, 0.8f, 1.0f, 0.25f, 0.001f);
  records::RecordSet dirty = clean;
  AddRecord(dirty, 0, 3, std::nanf(""), 0.3f, 1.0f, 0.001f);  // below V_min = 0.5
  AddRecord(dirty, 0, 4, HUGE_VALF, 1.0f, 1.0f, 0.001f);
  dirty.flags[3] = records::kFlagInvalidated;
  for (FusionMode mode : {FusionMode::kBlend, FusionMode::kNearest}) {
    WeightingProfile p;
    p.mode = mode;
    auto want = Fuse(clean, 1, 0.02, p);
    auto got = Fuse(dirty, 1, 0.02, p);
    ASSERT_TRUE(want.ok() && got.ok());
    const auto& a = want->by_modality.at(Modality::kRgb);
    const auto& b = got->by_modality.at(Modality::kRgb);
    EXPECT_EQ(b.value, a.value);
    EXPECT_EQ(b.weight, a.weight);
    EXPECT_EQ(b.uncertainty, a.uncertainty);
    EXPECT_TRUE(std::isfinite(b.value[0]) && std::isfinite(b.uncertainty[0]));
  }
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

// Claim (§7): per vossel and fused channel, C_k, Σw and U_k are the plain weighted sums of
// that channel's records with w > 0 (RecordWeights), a_{m,c} applied to each value; kNearest
// takes the first record of the greatest weight. Bit for bit: the sums taken one record at a
// time in the records' order, in doubles, as Fuse takes them. Records of several modalities
// interleave in a vossel (sorted by source), as a stored project's do; some have no weight,
// some vossels have none at all.
TEST(FuseTest, EqualsThePlainSumsPerVosselAndChannel) {
  std::mt19937 rng(11);
  std::uniform_real_distribution<float> unit(0.0f, 1.0f);
  const Modality kinds[] = {Modality::kLidar, Modality::kRgb, Modality::kDerived, Modality::kIr,
                            Modality::kRadar};
  records::RecordSet s;
  const int vossels = 3000;
  for (int k = 0; k < vossels; ++k) {
    const int n = k % 11;  // 0 to 10 records
    for (int m = 0; m < n; ++m) {
      AddRecord(s, k, 1 + m, unit(rng), unit(rng), unit(rng), 0.02f * unit(rng));
      const Modality kind = kinds[(k + m * 3) % 5];
      s.modality.back() = int8_t(kind);
      s.flags.back() = kind == Modality::kDerived ? records::kFlagDerived : 0;
      s.range_m.back() = 1.0f + 9.0f * unit(rng);
      for (int c = 0; c < 3; ++c) s.value[(s.size() - 1) * 3 + c] = 2.0f * unit(rng);
    }
  }
  for (FusionMode mode : {FusionMode::kBlend, FusionMode::kNearest}) {
    WeightingProfile p;
    p.mode = mode;
    p.alpha = 1.3;
    p.channel_gain[4] = {0.5, 2.0, 1.5};
    auto w = RecordWeights(s, vossels, 0.02, p);
    auto fused = Fuse(s, vossels, 0.02, p);
    ASSERT_TRUE(w.ok() && fused.ok());
    int64_t checked = 0;
    for (int k = 0; k < vossels; ++k) {
      for (const auto& [kind, f] : fused->by_modality) {
        double sw = 0.0, best = 0.0;
        std::array<double, 3> wc{}, wcc{}, best_v{};
        for (size_t i = w->begin[k]; i < w->begin[k + 1]; ++i) {
          if (records::FusedChannelOf(Modality(s.modality[i])) != kind) continue;
          const double wi = w->weight[i];
          if (!(wi > 0.0)) continue;
          auto gain = p.channel_gain.find(s.scan[i]);
          std::array<double, 3> v;
          for (int c = 0; c < 3; ++c) {
            v[c] = (gain == p.channel_gain.end() ? 1.0 : double(float(gain->second[c]))) *
                   s.value[i * 3 + c];
          }
          sw += wi;
          for (int c = 0; c < 3; ++c) {
            wc[c] += wi * v[c];
            wcc[c] += wi * v[c] * v[c];
          }
          if (wi > best) {
            best = wi;
            best_v = v;
          }
        }
        ASSERT_EQ(f.weight[k], float(sw)) << "vossel " << k;
        if (sw == 0.0) continue;
        double variance = 0.0;
        for (int c = 0; c < f.channels; ++c) {
          const double mean = wc[c] / sw;
          variance += std::max(0.0, wcc[c] / sw - mean * mean);
          const double want = mode == FusionMode::kNearest ? best_v[c] : mean;
          ASSERT_EQ(f.value[k * f.channels + c], float(want))
              << "vossel " << k << " channel " << c;
        }
        variance /= f.channels;
        ASSERT_EQ(f.uncertainty[k], float(std::sqrt(variance + 1.0 / sw))) << "vossel " << k;
        ++checked;
      }
    }
    std::printf("mode %d: %lld (vossel, channel) pairs with weight checked\n", int(mode),
                static_cast<long long>(checked));
    EXPECT_GT(checked, vossels);  // several channels per vossel, most with weight
  }
}

}  // namespace
}  // namespace vasl::fusion

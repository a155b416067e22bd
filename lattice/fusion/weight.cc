#include "lattice/fusion/weight.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>

#include "lattice/geometry/footprint.h"

namespace vasl::fusion {
namespace {

/// Records per run of the kernel's passes: its scratch columns stay in L1.
constexpr size_t kBlock = 256;

inline float FloatOfBits(int32_t bits) {
  float f;
  std::memcpy(&f, &bits, sizeof f);
  return f;
}
inline int32_t BitsOfFloat(float f) {
  int32_t bits;
  std::memcpy(&bits, &f, sizeof bits);
  return bits;
}

/// ln x for normal x > 0, −∞ for x ≤ 0, subnormal or NaN. x = m·2^e with m in [√½, √2), then
/// ln(1 + f) for f = m − 1 by the minimax polynomial of Cephes' logf (relative error below
/// 2·10⁻⁷). Branch-free, so that the loops calling it vectorise.
[[gnu::always_inline]] inline float Ln(float x) {
  const int32_t bits = BitsOfFloat(x);
  int32_t e = ((bits >> 23) & 0xff) - 126;                    // x = m·2^e, m in [½, 1)
  float m = FloatOfBits((bits & 0x007fffff) | 0x3f000000);
  const bool low = m < 0.707106781186547524f;
  e -= low ? 1 : 0;
  m = low ? m + m - 1.0f : m - 1.0f;
  const float z = m * m;
  float y = 7.0376836292e-2f;
  y = y * m - 1.1514610310e-1f;
  y = y * m + 1.1676998740e-1f;
  y = y * m - 1.2420140846e-1f;
  y = y * m + 1.4249322787e-1f;
  y = y * m - 1.6668057665e-1f;
  y = y * m + 2.0000714765e-1f;
  y = y * m - 2.4999993993e-1f;
  y = y * m + 3.3333331174e-1f;
  y *= m * z;
  const float ef = float(e);
  y += -2.12194440e-4f * ef;  // ln 2 split in two so that e·ln 2 keeps its digits
  y += -0.5f * z;
  const float r = m + y + 0.693359375f * ef;
  return x >= std::numeric_limits<float>::min() ? r : -std::numeric_limits<float>::infinity();
}

/// e^x for x ≤ 0 as the kernel needs it (and up to 88): 2^n·e^r with |r| ≤ ½ ln 2 and the
/// polynomial of Cephes' expf (relative error below 2·10⁻⁷); exactly 0 below −87 (−∞, NaN too).
[[gnu::always_inline]] inline float Exp(float x) {
  const float xc = std::min(std::max(x, -87.0f), 88.0f);
  constexpr float kRound = 12582912.0f;  // 1.5·2²³: adding it rounds to an integer
  const float n = (xc * 1.44269504088896341f + kRound) - kRound;
  float r = xc - n * 0.693359375f;
  r -= n * -2.12194440e-4f;
  float y = 1.9875691500e-4f;
  y = y * r + 1.3981999507e-3f;
  y = y * r + 8.3334519073e-3f;
  y = y * r + 4.1665795894e-2f;
  y = y * r + 1.6666665459e-1f;
  y = y * r + 5.0000001201e-1f;
  y = y * (r * r) + r + 1.0f;
  const float scale = FloatOfBits((int32_t(n) + 127) << 23);
  return x > -87.0f ? y * scale : 0.0f;
}

/// The gates of §7 ([V ≥ V_min], V > 0, [θ ≤ θ_max], not invalidated) times λ_src for derived
/// records, for m records; the pointers do not alias, so that the loop vectorises.
[[gnu::always_inline]] inline void Gates(const float* __restrict vis,
                                         const float* __restrict cos_inc,
                                         const int8_t* __restrict flags, size_t m, float v_min,
                                         float cos_max, float lambda_src,
                                         float* __restrict product) {
  for (size_t i = 0; i < m; ++i) {
    const float v = vis[i];
    const int32_t f = flags[i];
    const bool pass = (v >= v_min) & (v > 0.0f) & (std::max(cos_inc[i], 0.0f) >= cos_max) &
                      ((f & records::kFlagInvalidated) == 0);
    const float source = (f & records::kFlagDerived) ? lambda_src : 1.0f;
    product[i] = pass ? source : 0.0f;
  }
}

/// The confidence factors of m records (kConfidenceCount per record) transposed into
/// out[f * kBlock + i], 4 records at a time in registers: the factor passes then read
/// contiguous columns.
[[gnu::always_inline]] inline void TransposeConfidence(const float* __restrict conf, size_t m,
                                                       float* __restrict out) {
  static_assert(records::kConfidenceCount == 6, "the shuffles below take 6 factors");
  typedef float V4 __attribute__((vector_size(16)));
  // Lanes 0-3 of a then 4-7 of b, picked by index: GCC's and clang's spelling of one shuffle
  // (clang compiles this file for deploy/fuzz.sh's harnesses).
#if defined(__clang__)
#define VASL_SHUFFLE(a, b, i0, i1, i2, i3) __builtin_shufflevector(a, b, i0, i1, i2, i3)
#else
  typedef int32_t I4 __attribute__((vector_size(16)));
#define VASL_SHUFFLE(a, b, i0, i1, i2, i3) __builtin_shuffle(a, b, I4{i0, i1, i2, i3})
#endif
  const auto load = [](const float* p) {
    V4 v;
    std::memcpy(&v, p, sizeof v);
    return v;
  };
  size_t i = 0;
  for (; i + 4 <= m; i += 4) {
    const float* q = conf + i * 6;
    const V4 v0 = load(q), v1 = load(q + 4), v2 = load(q + 8);
    const V4 v3 = load(q + 12), v4 = load(q + 16), v5 = load(q + 20);
    // Records 0-3, factors 0-3 in r0..r3; factors 4-5 of records 0-1 and 2-3 in h01, h23.
    const V4 r1 = VASL_SHUFFLE(v1, v2, 2, 3, 4, 5);
    const V4 r3 = VASL_SHUFFLE(v4, v5, 2, 3, 4, 5);
    const V4 h01 = VASL_SHUFFLE(v1, v2, 0, 1, 6, 7);
    const V4 h23 = VASL_SHUFFLE(v4, v5, 0, 1, 6, 7);
    const V4 t0 = VASL_SHUFFLE(v0, r1, 0, 4, 1, 5);
    const V4 t1 = VASL_SHUFFLE(v0, r1, 2, 6, 3, 7);
    const V4 t2 = VASL_SHUFFLE(v3, r3, 0, 4, 1, 5);
    const V4 t3 = VASL_SHUFFLE(v3, r3, 2, 6, 3, 7);
    const V4 f[6] = {VASL_SHUFFLE(t0, t2, 0, 1, 4, 5),
                     VASL_SHUFFLE(t0, t2, 2, 3, 6, 7),
                     VASL_SHUFFLE(t1, t3, 0, 1, 4, 5),
                     VASL_SHUFFLE(t1, t3, 2, 3, 6, 7),
                     VASL_SHUFFLE(h01, h23, 0, 2, 4, 6),
                     VASL_SHUFFLE(h01, h23, 1, 3, 5, 7)};
    for (int k = 0; k < 6; ++k) std::memcpy(out + k * kBlock + i, &f[k], sizeof f[k]);
  }
#undef VASL_SHUFFLE
  for (; i < m; ++i) {
    for (int k = 0; k < 6; ++k) out[k * kBlock + i] = conf[i * 6 + k];
  }
}

/// The smallest float f with double(f) ≥ x, so that `float ≥ f` tests `double(float) ≥ x`.
float FloatAtLeast(double x) {
  float f = float(x);
  if (double(f) < x) f = std::nextafter(f, std::numeric_limits<float>::infinity());
  return f;
}

}  // namespace

WeightColumns WeightColumns::Of(const records::RecordSet& r, size_t first) {
  WeightColumns c;
  c.vis = r.vis.data() + first;
  c.cos_inc = r.cos_inc.data() + first;
  c.foot_major_m = r.foot_major_m.data() + first;
  c.foot_minor_m = r.foot_minor_m.data() + first;
  c.conf = r.conf.data() + first * records::kConfidenceCount;
  c.scan = r.scan.data() + first;
  c.flags = r.flags.data() + first;
  c.range_m = r.range_m.data() + first;
  return c;
}

WeightKernel::Factor WeightKernel::FactorOf(double exponent) {
  if (exponent == 0.0) return {Power::kOff, 0.0f};
  if (exponent == 1.0) return {Power::kOne, 1.0f};
  if (exponent == 2.0) return {Power::kTwo, 2.0f};
  return {Power::kLog, float(exponent)};
}

WeightKernel::WeightKernel(const WeightingProfile& p, double target_m)
    : vis_(FactorOf(p.beta)), cos_(FactorOf(p.alpha)), range_(FactorOf(p.rho)) {
  for (int f = 0; f < records::kConfidenceCount; ++f) conf_[f] = FactorOf(p.kappa[f]);
  any_log_ = vis_.power == Power::kLog || cos_.power == Power::kLog ||
             range_.power == Power::kLog;
  for (const Factor& f : conf_) {
    any_log_ = any_log_ || f.power == Power::kLog;
    any_conf_ = any_conf_ || f.power != Power::kOff;
  }
  v_min_ = FloatAtLeast(p.v_min);
  if (p.theta_max_rad > 0.0) cos_max_ = FloatAtLeast(std::cos(p.theta_max_rad));
  target_m_ = float(target_m);
  lambda_src_ = float(p.lambda_src);
  proximity_ = p.proximity_m > 0.0 ? float(1.0 / p.proximity_m) : 0.0f;
  int32_t max_id = -1;
  for (const auto& [id, g] : p.scan_gain) max_id = std::max(max_id, id);
  gain_.assign(size_t(max_id + 1), 1.0f);
  for (const auto& [id, g] : p.scan_gain) {
    if (id >= 0) gain_[size_t(id)] = float(g);
  }
}

[[gnu::always_inline]] inline void WeightKernel::Apply(Factor f, const float* __restrict x,
                                                      size_t n, float* __restrict product,
                                                      float* __restrict log_sum) {
  switch (f.power) {
    case Power::kOff:
      return;
    case Power::kOne:
      for (size_t i = 0; i < n; ++i) product[i] *= x[i];
      return;
    case Power::kTwo:
      for (size_t i = 0; i < n; ++i) product[i] *= x[i] * x[i];
      return;
    case Power::kLog:
      for (size_t i = 0; i < n; ++i) log_sum[i] += f.exponent * Ln(x[i]);
      return;
  }
}

[[gnu::always_inline]] inline void WeightKernel::Body(const WeightColumns& c, size_t n,
                                                     float* w) const {
  float product[kBlock], log_sum[kBlock], x[kBlock], conf[records::kConfidenceCount * kBlock];
  const size_t gains = gain_.size();
  for (size_t b = 0; b < n; b += kBlock) {
    const size_t m = std::min(kBlock, n - b);
    Gates(c.vis + b, c.cos_inc + b, c.flags + b, m, v_min_, cos_max_, lambda_src_, product);
    std::fill_n(log_sum, m, 0.0f);
    if (gains > 0) {
      for (size_t i = 0; i < m; ++i) {
        const int32_t s = c.scan[b + i];
        if (s >= 0 && size_t(s) < gains) product[i] *= gain_[size_t(s)];
      }
    }
    Apply(vis_, c.vis + b, m, product, log_sum);
    if (cos_.power != Power::kOff) {
      for (size_t i = 0; i < m; ++i) x[i] = std::max(c.cos_inc[b + i], 0.0f);
      Apply(cos_, x, m, product, log_sum);
    }
    if (range_.power != Power::kOff) {
      for (size_t i = 0; i < m; ++i) {
        x[i] = geometry::RangeWeight<float>(c.foot_major_m[b + i], c.foot_minor_m[b + i],
                                            target_m_);
      }
      Apply(range_, x, m, product, log_sum);
    }
    if (any_conf_) {
      TransposeConfidence(c.conf + b * records::kConfidenceCount, m, conf);
      for (int f = 0; f < records::kConfidenceCount; ++f) {
        Apply(conf_[f], conf + f * kBlock, m, product, log_sum);
      }
    }
    if (proximity_ > 0.0f) {
      for (size_t i = 0; i < m; ++i) {
        log_sum[i] -= (c.range_m[b + i] - c.range_min_m[b + i]) * proximity_;
      }
    }
    if (any_log_ || proximity_ > 0.0f) {
      for (size_t i = 0; i < m; ++i) w[b + i] = product[i] * Exp(log_sum[i]);
    } else {
      std::copy_n(product, m, w + b);
    }
  }
}

// The body compiled for the baseline (SSE2, 4 lanes), for AVX2 (8 lanes) and for x86-64-v4
// (AVX-512: 16 lanes; one core of an AMD EPYC under the general profile, 47 M records/s
// baseline, 85 M AVX2, 117 M AVX-512: BM_WeightKernelOneThread/general_*), each call taking
// memory::WidestIsa. Every variant rounds alike (memory/isa.h: -ffp-contract=off), so the
// weights do not depend on the CPU (WeightTest.EveryInstructionSetGivesTheSameBits). The wider
// variants exist where VASL_ISA_VARIANTS is 1.

void WeightKernel::EvaluateBaseline(const WeightColumns& c, size_t n, float* w) const {
  Body(c, n, w);
}
#if VASL_ISA_VARIANTS
[[gnu::target("avx2")]] void WeightKernel::EvaluateAvx2(const WeightColumns& c, size_t n,
                                                       float* w) const {
  Body(c, n, w);
}
[[gnu::target("arch=x86-64-v4")]] void WeightKernel::EvaluateX86_64_V4(const WeightColumns& c,
                                                                      size_t n, float* w) const {
  Body(c, n, w);
}
#endif

void WeightKernel::EvaluateOn(Isa isa, const WeightColumns& c, size_t n, float* w) const {
#if VASL_ISA_VARIANTS
  if (isa == Isa::kX86_64_V4) return EvaluateX86_64_V4(c, n, w);
  if (isa == Isa::kAvx2) return EvaluateAvx2(c, n, w);
#endif
  (void)isa;
  EvaluateBaseline(c, n, w);
}

void WeightKernel::Evaluate(const WeightColumns& c, size_t n, float* w) const {
  EvaluateOn(memory::WidestIsa(), c, n, w);
}

double RecordWeight(const WeightingProfile& p, const WeightInputs& in, double target_m) {
  float conf[records::kConfidenceCount];
  std::fill(std::begin(conf), std::end(conf), 1.0f);
  if (in.conf != nullptr) std::copy_n(in.conf, records::kConfidenceCount, conf);
  const int8_t flags = in.derived ? records::kFlagDerived : 0;
  WeightColumns c;
  c.vis = &in.vis;
  c.cos_inc = &in.cos_inc;
  c.foot_major_m = &in.foot_major_m;
  c.foot_minor_m = &in.foot_minor_m;
  c.conf = conf;
  c.scan = &in.scan;
  c.flags = &flags;
  c.range_m = &in.range_m;
  c.range_min_m = &in.range_min_m;
  float w = 0.0f;
  WeightKernel(p, target_m).Evaluate(c, 1, &w);
  return w;
}

}  // namespace vasl::fusion

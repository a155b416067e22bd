/// @file weight.h
/// @brief The record weight w_{k,m} of VASL-MODEL §7: the one implementation every path
///        (ingest fusion, reweight, render blending) calls.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <vector>

#include "lattice/fusion/profile.h"
#include "lattice/memory/isa.h"
#include "lattice/records/records.h"

namespace vasl::fusion {

/// The inputs of one record's weight, all read from the record itself (§6).
struct WeightInputs {
  float vis = 0.0f;             ///< V
  float cos_inc = 0.0f;         ///< cosθ
  float foot_major_m = 0.0f;    ///< s_major
  float foot_minor_m = 0.0f;    ///< s_minor
  const float* conf = nullptr;  ///< records::kConfidenceCount factors
  int32_t scan = 0;             ///< source id, for g_m
  bool derived = false;         ///< derived (λ_src) or raw
  float range_m = 0.0f;         ///< r_{k,m}, for the proximity term
  float range_min_m = 0.0f;     ///< r_{k,min} over the vossel's records of the same channel
};

/// The weight inputs of record `i` of `records` (§6 fields); `range_min_m` is r_{k,min} of its
/// vossel and channel (used by the proximity term only).
inline WeightInputs WeightInputsOf(const records::RecordSet& records, size_t i,
                                   float range_min_m = 0.0f) {
  WeightInputs in;
  in.vis = records.vis[i];
  in.cos_inc = records.cos_inc[i];
  in.foot_major_m = records.foot_major_m[i];
  in.foot_minor_m = records.foot_minor_m[i];
  in.conf = &records.conf[i * records::kConfidenceCount];
  in.scan = records.scan[i];
  in.derived = (records.flags[i] & records::kFlagDerived) != 0;
  in.range_m = records.range_m[i];
  in.range_min_m = range_min_m;
  return in;
}

/// The columns of a run of records that the §7 weight reads (§6 fields), structure of arrays:
/// record i's fields are vis[i], cos_inc[i], …, conf[i * kConfidenceCount + f].
struct WeightColumns {
  const float* vis = nullptr;
  const float* cos_inc = nullptr;
  const float* foot_major_m = nullptr;
  const float* foot_minor_m = nullptr;
  const float* conf = nullptr;  ///< kConfidenceCount per record
  const int32_t* scan = nullptr;
  const int8_t* flags = nullptr;  ///< RecordFlag bits: invalidated records weigh 0, derived λ_src
  const float* range_m = nullptr;      ///< read by the proximity term only
  const float* range_min_m = nullptr;  ///< r_{k,min} per record; proximity term only
  /// The columns of records [first, …) of `records` (range_min_m not set).
  static WeightColumns Of(const records::RecordSet& records, size_t first = 0);
};

/// §7: w = [V ≥ V_min]·V^β·max(cosθ,0)^α·K_range^ρ·Π_f conf_f^κ_f·g_m·λ_src
///       [·[θ ≤ θ_max]]·[·exp(−(r − r_min)/ρ_p)], with K_range from §4.2 and s* = h/2: the one
/// implementation, evaluated over runs of records as flat float arrays (RecordWeights) or for
/// one record (RecordWeight).
/// @details A factor with exponent 0 is left out (x⁰ = 1, also for x = 0), exponents 1 and 2
///          multiply, and every other exponent goes into one exponential of a sum of logarithms,
///          exp(Σ e·ln x + proximity), so that a record costs one exp and no pow whatever the
///          profile. ln and exp are float polynomials (relative error below 2·10⁻⁷ each); a zero
///          factor under a positive exponent gives exactly 0.
class WeightKernel {
 public:
  /// The instruction sets Evaluate is compiled for, one variant each (memory/isa.h): every
  /// variant rounds every operation alike, so the weights are the same bits on every CPU.
  using Isa = memory::Isa;
  /// `target_m` is s*.
  WeightKernel(const WeightingProfile& profile, double target_m);
  /// w[i] for the n records of `columns` (range_min_m is needed only with the proximity term),
  /// by the widest variant this CPU runs (memory::WidestIsa: x86-64-v4's AVX-512, AVX2, or the
  /// baseline's SSE2).
  void Evaluate(const WeightColumns& columns, size_t n, float* w) const;
  /// The same by `isa`'s variant, which the CPU must support (memory::Supports; tests and
  /// benchmarks compare them).
  void EvaluateOn(Isa isa, const WeightColumns& columns, size_t n, float* w) const;
  bool uses_range_min() const { return proximity_ > 0.0f; }

 private:
  /// Evaluate's body, inlined into one function per Isa (weight.cc).
  void Body(const WeightColumns& c, size_t n, float* w) const;
  void EvaluateBaseline(const WeightColumns& c, size_t n, float* w) const;
  /// The wider variants, defined where VASL_ISA_VARIANTS is 1 (memory/isa.h).
  void EvaluateAvx2(const WeightColumns& c, size_t n, float* w) const;
  void EvaluateX86_64_V4(const WeightColumns& c, size_t n, float* w) const;
  /// How one factor x^e enters: left out, multiplied (e = 1, 2) or through ln x (other e).
  enum class Power : int8_t { kOff, kOne, kTwo, kLog };
  struct Factor {
    Power power = Power::kOff;
    float exponent = 0.0f;
  };
  static Factor FactorOf(double exponent);
  static void Apply(Factor f, const float* x, size_t n, float* product, float* log_sum);

  Factor vis_, cos_, range_;
  std::array<Factor, records::kConfidenceCount> conf_;
  bool any_log_ = false, any_conf_ = false;
  float v_min_ = 0.0f, cos_max_ = -1.0f, target_m_ = 0.0f, lambda_src_ = 1.0f;
  float proximity_ = 0.0f;  ///< 1/ρ_p; 0: off
  std::vector<float> gain_;  ///< g_m by source id; ids past its end: 1
};

/// The §7 weight of one record (WeightKernel over a run of one), g_m from the profile.
double RecordWeight(const WeightingProfile& p, const WeightInputs& in, double target_m);

}  // namespace vasl::fusion

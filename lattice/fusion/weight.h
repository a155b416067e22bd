/// @file weight.h
/// @brief The record weight w_{k,m} of VASL-MODEL §7: the one implementation every path
///        (ingest fusion, reweight, render blending) calls.
#pragma once

#include <cmath>
#include <cstddef>

#include "lattice/fusion/profile.h"
#include "lattice/geometry/footprint.h"
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

/// x^e with exact fast paths for the common exponents 0, 1 and 2 (RECORDS-NOTES: the powf calls,
/// not memory, bound a reweight).
inline double PowFast(double x, double e) {
  if (e == 1.0) return x;
  if (e == 0.0) return 1.0;
  if (e == 2.0) return x * x;
  return x > 0.0 ? std::pow(x, e) : 0.0;
}

/// §7: w = [V ≥ V_min]·V^β·max(cosθ,0)^α·K_range^ρ·Π_f conf_f^κ_f·g_m·λ_src
///       [·[θ ≤ θ_max]]·[·exp(−(r − r_min)/ρ_p)], with K_range from §4.2 and s* = h/2.
/// `target_m` is s*. `gain` is g_m looked up by the caller (1 when the profile has none).
inline double RecordWeight(const WeightingProfile& p, const WeightInputs& in, double target_m,
                           double gain) {
  if (in.vis < p.v_min || in.vis <= 0.0f) return 0.0;
  const double cos_inc = std::max(0.0, double(in.cos_inc));
  if (p.theta_max_rad > 0.0 && cos_inc < std::cos(p.theta_max_rad)) return 0.0;
  const double k_range =
      geometry::RangeWeight({in.foot_major_m, in.foot_minor_m}, target_m);
  double w = PowFast(in.vis, p.beta) * PowFast(cos_inc, p.alpha) * PowFast(k_range, p.rho);
  if (in.conf != nullptr) {
    for (int f = 0; f < records::kConfidenceCount; ++f) w *= PowFast(in.conf[f], p.kappa[f]);
  }
  w *= gain * (in.derived ? p.lambda_src : 1.0);
  if (p.proximity_m > 0.0) w *= std::exp(-(in.range_m - in.range_min_m) / p.proximity_m);
  return w;
}

}  // namespace vasl::fusion

/// @file profile.h
/// @brief Weighting profiles (VASL-MODEL §7): named, versioned parameter sets of the weight.
#pragma once

#include <array>
#include <cstdint>
#include <map>
#include <string>

#include "absl/status/status.h"
#include "lattice/records/records.h"

namespace vasl::fusion {

/// How records of one vossel combine (§7).
enum class FusionMode { kBlend, kNearest };

/// The parameters of w_{k,m} (§7). Defaults are the model's defaults.
struct WeightingProfile {
  std::string name = "default";
  int32_t version = 1;
  double alpha = 1.0;       ///< α, incidence exponent (1: Lambertian foreshortening)
  double beta = 1.0;        ///< β, penumbra exponent on V
  double rho = 1.0;         ///< ρ, range exponent on K_range
  std::array<double, records::kConfidenceCount> kappa = {1.0, 1.0, 1.0, 1.0};  ///< κ_f
  double v_min = 0.5;       ///< V_min: records with V below it get weight 0
  double lambda_src = 0.5;  ///< λ_src for derived records (raw records: 1)
  double theta_max_rad = 0.0;   ///< optional incidence cut-off θ_max; 0: off
  double proximity_m = 0.0;     ///< optional nearest-view proximity scale ρ_p, metres; 0: off
  std::map<int32_t, double> scan_gain;  ///< g_m per source id; missing: 1
  FusionMode mode = FusionMode::kBlend;
};

/// INVALID_ARGUMENT when a parameter is out of range (negative exponents, V_min outside [0, 1],
/// non-finite values).
absl::Status ValidateProfile(const WeightingProfile& profile);

}  // namespace vasl::fusion

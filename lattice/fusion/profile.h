/// @file profile.h
/// @brief Weighting profiles (VASL-MODEL §7): named, versioned parameter sets of the weight.
#pragma once

#include <array>
#include <cstdint>
#include <map>
#include <string>


#include <memory>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "lattice/fusion/lens.h"
#include "lattice/records/records.h"

namespace vasl::fusion {

/// How records of one vossel combine (§7).
enum class FusionMode { kBlend, kNearest };

/// κ values a profile written before smear and fog had their own factors gives (§9): the first
/// four; the rest keep 1.
inline constexpr size_t kOlderKappaCount = 4;

/// The parameters of w_{k,m} (§7). Defaults are the model's defaults.
struct WeightingProfile {
  std::string name = "default";
  int32_t version = 1;      ///< revision: creating a profile under an existing name adds one
  double alpha = 1.0;       ///< α, incidence exponent (1: Lambertian foreshortening)
  double beta = 1.0;        ///< β, penumbra exponent on V
  double rho = 1.0;         ///< ρ, range exponent on K_range
  /// κ_f per confidence factor, in records::ConfidenceFactor order.
  std::array<double, records::kConfidenceCount> kappa = {1.0, 1.0, 1.0, 1.0, 1.0, 1.0};
  double v_min = 0.5;       ///< V_min: records with V below it get weight 0
  double lambda_src = 0.5;  ///< λ_src for derived records (raw records: 1)
  double theta_max_rad = 0.0;   ///< optional incidence cut-off θ_max; 0: off
  double proximity_m = 0.0;     ///< optional nearest-view proximity scale ρ_p, metres; 0: off
  std::map<int32_t, double> scan_gain;  ///< g_m per source id, a gain on the weight; missing: 1
  /// a_{m,c}: per source id, a radiometric gain on each value channel of its records (§7,
  /// multi-scan normalisation); C_{k,m,c} is fused as a_{m,c}·C_{k,m,c}. Missing: 1.
  std::map<int32_t, std::array<double, records::kValueChannels>> channel_gain;
  FusionMode mode = FusionMode::kBlend;
  /// §9 lens dirt and fog: catalog ids of the LensMaps the profile applies (a later map wins
  /// for a source two maps list). Stored with the profile.
  std::vector<int64_t> lens_maps;
  /// `lens_maps` resolved (reweight::LoadProfile does it); fusion refuses a profile whose maps
  /// are listed but not resolved. Not stored.
  std::shared_ptr<const LensTable> lens;
};

/// The built-in profile every project starts with: the model's defaults, name "default",
/// revision 1. Its fused values are the "fused-default" layer of every tile.
inline constexpr char kDefaultProfileName[] = "default";

/// A profile as the catalog stores it: one "key values..." line per parameter, numbers written
/// so that they read back bit for bit (%.17g).
std::string ProfileToText(const WeightingProfile& profile);
/// Reads ProfileToText's output. DATA_LOSS for text it did not write.
absl::StatusOr<WeightingProfile> ProfileFromText(const std::string& text);

/// INVALID_ARGUMENT when a parameter is out of range (negative exponents, V_min outside [0, 1],
/// non-finite values, gains a_{m,c} ≤ 0) or the name is not 1-63 characters of [A-Za-z0-9._-].
absl::Status ValidateProfile(const WeightingProfile& profile);

}  // namespace vasl::fusion

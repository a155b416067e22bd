/// @file profiles.h
/// @brief Weighting profiles of a project (VASL-MODEL §7): named revisions kept in the catalog,
///        the active one, and which profiles' fused layers a version keeps up to date.
#pragma once

#include <map>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "lattice/fusion/profile.h"
#include "lattice/records/records.h"
#include "lattice/store/project_store.h"

namespace vasl::reweight {

/// A stored profile revision with the time it was made.
struct NamedProfile {
  fusion::WeightingProfile profile;
  std::string created_utc;  ///< empty for the built-in default
};

/// Lens map `id` (§9) from the catalog, with its id and time. NOT_FOUND for an unknown id.
absl::StatusOr<fusion::LensMap> LoadLensMap(const store::ProjectStore& store, int64_t id);
/// Every lens map of the project, oldest first.
absl::StatusOr<std::vector<fusion::LensMap>> ListLensMaps(const store::ProjectStore& store);

/// Loads the §9 lens maps `profile.lens_maps` names from the catalog into `profile.lens`
/// (null when it names none). NOT_FOUND for an id the catalog lacks.
absl::Status ResolveLensMaps(const store::ProjectStore& store, fusion::WeightingProfile& profile);

/// Profile `name` at `revision` (0: the latest), its lens maps resolved. "default" is built in (the model's
/// defaults, revision 1). NOT_FOUND for an unknown name or revision.
absl::StatusOr<NamedProfile> LoadProfile(const store::ProjectStore& store, const std::string& name,
                                         int32_t revision = 0);

/// Stores `profile` as the next revision of its name and returns it with that revision.
/// INVALID_ARGUMENT for parameters out of range or the reserved name "default".
absl::StatusOr<NamedProfile> CreateProfile(store::ProjectStore& store,
                                           fusion::WeightingProfile profile);

/// The built-in default, then the latest revision of every stored profile by name.
absl::StatusOr<std::vector<NamedProfile>> ListProfiles(const store::ProjectStore& store);

/// The profiles, besides the default, whose fused layers a new version must hold for the
/// tiles it rewrites: every profile with a fused layer in `head` (complete or not), and the
/// project's active profile. A flow that changes records fuses them under each.
absl::StatusOr<std::vector<fusion::WeightingProfile>> MaintainedProfiles(
    const store::ProjectStore& store, const store::Manifest& head);

/// §7 fusion of `records` under each of `profiles`, keyed by fused layer name
/// (store::FusedLayerName), as store::Snapshot::profile_fused holds it.
absl::StatusOr<std::map<std::string, records::FusedValues>> FuseProfiles(
    const records::RecordSet& records, size_t vossel_count, double vossel_size_m,
    const std::vector<fusion::WeightingProfile>& profiles);

}  // namespace vasl::reweight

/// @file lens_flow.h
/// @brief The lens flow (VASL-MODEL §9): find a rig camera's dirt and fog map from its frames
///        of a period, keep it in the catalog and store a profile revision that applies it, so
///        that applying it, to scans ingested before it too, is a reweight.
#pragma once

#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "lattice/reweight/lens_estimate.h"
#include "lattice/reweight/profiles.h"
#include "lattice/store/project_store.h"

namespace vasl::reweight {

/// Which frames a lens map is found from and applies to.
struct LensRequest {
  std::string rig;         ///< the rig, as the scans name it (required)
  std::string camera;      ///< the camera's source name; empty: the rig's only camera name
  std::string from_utc;    ///< the period: scans captured at or after (ISO 8601); empty: open
  std::string to_utc;      ///< scans captured at or before; empty: open
  std::string name;        ///< the profile to store; empty: base's name ("lens" for default)
  LensOptions options;
};

struct LensOutcome {
  NamedProfile profile;        ///< the new revision, applying the map
  int64_t map_id = 0;          ///< the map's catalog id
  LensEstimate estimate;       ///< the map and what went into it
  std::vector<LensFrame> frames;
  int64_t replaced_map = 0;    ///< the map of the same rig and camera the base applied; 0: none
};

/// Finds the lens map of `request.rig`'s camera from the camera sources of the rig's scans in
/// `snapshot` captured in the period (EstimateLensMap, weighed under `base` without any map it
/// applies to the same rig and camera), stores it, and stores `base` applying it (in place of
/// such a map) as a new revision of the profile. INVALID_ARGUMENT for a missing rig, a rig with
/// several camera names and none given, or a period that is not ISO 8601; NOT_FOUND when no
/// scan of the rig falls in the period; FAILED_PRECONDITION for fewer than two frames.
absl::StatusOr<LensOutcome> EstimateLensProfile(store::ProjectStore& store,
                                                const store::Snapshot& snapshot,
                                                const fusion::WeightingProfile& base,
                                                const LensRequest& request);

}  // namespace vasl::reweight

/// @file normalise_flow.h
/// @brief The normalisation flow (VASL-MODEL §7): solve per-source per-channel gains on a
///        version's RGB records under a profile, and store them as a new profile revision, so
///        that normalising is a reweight.
#pragma once

#include <string>

#include "absl/status/statusor.h"
#include "lattice/reweight/normalise.h"
#include "lattice/reweight/profiles.h"
#include "lattice/store/project_store.h"

namespace vasl::reweight {

struct NormaliseOutcome {
  NamedProfile profile;   ///< the new revision, holding the gains
  NormaliseResult solve;  ///< what the solver used and achieved
};

/// Weighs `snapshot`'s records under `base` (§7), solves the RGB gains a_{m,c}
/// (SolveChannelGains) and stores `base` with those gains as a new revision of profile
/// `name` (empty: base's name, or "normalised" when base is the built-in default).
absl::StatusOr<NormaliseOutcome> NormaliseProfile(store::ProjectStore& store,
                                                  const store::Snapshot& snapshot,
                                                  const fusion::WeightingProfile& base,
                                                  const std::string& name,
                                                  const NormaliseOptions& options = {});

}  // namespace vasl::reweight

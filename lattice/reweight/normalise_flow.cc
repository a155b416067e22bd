#include "lattice/reweight/normalise_flow.h"

#include "lattice/fusion/fuse.h"

namespace vasl::reweight {

absl::StatusOr<NormaliseOutcome> NormaliseProfile(store::ProjectStore& store,
                                                  const store::Snapshot& snapshot,
                                                  const fusion::WeightingProfile& base,
                                                  const std::string& name,
                                                  const NormaliseOptions& options) {
  absl::StatusOr<fusion::RecordWeightsResult> weights =
      fusion::RecordWeights(snapshot.records, snapshot.geometry.size(),
                            snapshot.geometry.vossel_size_m, base);
  if (!weights.ok()) return weights.status();
  absl::StatusOr<NormaliseResult> solve =
      SolveChannelGains(snapshot.records, weights->begin, weights->weight, options);
  if (!solve.ok()) return solve.status();
  fusion::WeightingProfile next = base;
  next.name = !name.empty() ? name
              : base.name == fusion::kDefaultProfileName ? std::string("normalised")
                                                         : base.name;
  next.channel_gain.clear();
  for (const auto& [source, gain] : solve->gain) next.channel_gain[source] = gain;
  absl::StatusOr<NamedProfile> made = CreateProfile(store, next);
  if (!made.ok()) return made.status();
  return NormaliseOutcome{std::move(*made), std::move(*solve)};
}

}  // namespace vasl::reweight

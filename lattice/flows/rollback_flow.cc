// The rollback flow (flows.h): a new version whose manifest is an earlier version's.
#include "absl/strings/str_cat.h"
#include "lattice/flows/change.h"
#include "lattice/flows/flows.h"

namespace vasl::flows {

absl::StatusOr<FlowResult> Rollback(store::ProjectStore& store, int64_t version,
                                    const StageFn& stage) {
  FlowResult result;
  internal::StageClock clock(result, stage);
  if (absl::Status stop = clock.Start("load version", 0.0); !stop.ok()) return stop;
  if (version <= 0 || version >= store.head_version()) {
    return absl::InvalidArgumentError(absl::StrCat("roll back to a version in [1, ",
                                                   store.head_version() - 1, "]; got ", version));
  }
  absl::StatusOr<std::shared_ptr<const store::Snapshot>> target = store.LoadSnapshot(version);
  if (!target.ok()) return target.status();
  store::CommitPlan plan;
  plan.made_by = absl::StrCat("rollback to version ", version);
  plan.rollback_to = version;
  store::Snapshot next = **target;
  if (absl::Status s = internal::CommitFlow(store, std::move(next), plan, result, clock); !s.ok()) {
    return s;
  }
  result.tiles_changed = 0;
  return result;
}

}  // namespace vasl::flows

// The back-projection flow (flows.h, VASL-MODEL §10): an image's pixels appended as derived
// records in a batch of their own. Geometry does not change, so no older source is revisited.
#include <numeric>

#include "absl/strings/str_cat.h"
#include "lattice/flows/change.h"
#include "lattice/flows/flows.h"

namespace vasl::flows {

absl::StatusOr<FlowResult> BackProject(store::ProjectStore& store, const store::Snapshot& head,
                                       const store::ScanInfo& info, ingest::DerivedSource image,
                                       const StageFn& stage) {
  FlowResult result;
  internal::StageClock clock(result, stage);
  if (head.version == 0 || head.geometry.size() == 0) {
    return absl::FailedPreconditionError(absl::StrCat(
        "project '", store.name(), "' has no geometry to back-project onto: ingest a scan first"));
  }
  if (info.sources.size() != 1 || info.sources[0].modality != records::Modality::kDerived) {
    return absl::InternalError("BackProject: the batch has exactly one derived source");
  }
  image.id = info.sources[0].id;
  image.batch = info.batch;
  internal::Change change;
  change.geometry = head.geometry;
  change.old_to_new.resize(head.geometry.size());
  std::iota(change.old_to_new.begin(), change.old_to_new.end(), 0);
  change.new_sources.derived.push_back(std::move(image));
  absl::StatusOr<std::vector<store::ScanInfo>> scans = store.ListScans(head.version);
  if (!scans.ok()) return scans.status();
  store::CommitPlan plan;
  plan.made_by = absl::StrCat("back-project ", info.name);
  plan.add_scan = info;
  absl::StatusOr<store::Snapshot> next =
      internal::Propagate(store, head, std::move(change), internal::SourcesOf(*scans),
                          /*max_image_pixels=*/0, plan, result, clock);
  if (!next.ok()) return next.status();
  if (result.pixels_back_projected == 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        "no pixel of the image lands on the project's geometry (", result.pixels_outside,
        " pixels with a depth fall outside every vossel): check the pose and the projection"));
  }
  if (absl::Status s = internal::CommitFlow(store, std::move(*next), plan, result, clock); !s.ok()) {
    return s;
  }
  return result;
}

}  // namespace vasl::flows

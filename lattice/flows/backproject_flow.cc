// The back-projection flow (flows.h, VASL-MODEL §10): an image's pixels appended as derived
// records in a batch of their own. Geometry does not change, so no older source is revisited.
#include <numeric>

#include "absl/strings/str_cat.h"
#include "lattice/flows/change.h"
#include "lattice/flows/flows.h"
#include "lattice/ingest/backproject.h"
#include "lattice/ingest/validate.h"

namespace vasl::flows {

absl::StatusOr<FlowResult> BackProject(store::ProjectStore& store, const store::Snapshot& head,
                                       const BackProjectInput& input, int64_t max_image_bytes,
                                       int64_t max_image_pixels, const StageFn& stage) {
  FlowResult result;
  internal::StageClock clock(result, stage);
  if (absl::Status stop = clock.Start("validate", 0.0); !stop.ok()) return stop;
  if (head.version == 0 || head.geometry.size() == 0) {
    return absl::FailedPreconditionError(absl::StrCat(
        "project '", store.name(), "' has no geometry to back-project onto: ingest a scan first"));
  }
  if (absl::Status s = ingest::ValidatePose(input.pose, "back-projection"); !s.ok()) return s;
  if (int64_t(input.image.size()) > max_image_bytes) {
    return absl::ResourceExhaustedError(absl::StrCat("image of ", input.image.size(),
                                                     " bytes exceeds the limit of ", max_image_bytes));
  }
  absl::StatusOr<ingest::DerivedImage> decoded = ingest::DecodeRgbzImage(input.image, max_image_pixels);
  if (!decoded.ok()) return decoded.status();
  if (input.pinhole) {
    if (absl::Status s = geometry::ValidatePinhole(input.intrinsics); !s.ok()) return s;
  }
  if (input.render_id > 0) {
    if (absl::StatusOr<store::RenderRecord> r = store.GetRender(input.render_id); !r.ok()) {
      return r.status();
    }
  }
  absl::StatusOr<int32_t> batch = store.NextBatchId();
  if (!batch.ok()) return batch.status();
  absl::StatusOr<int32_t> source_id = store.NextSourceId();
  if (!source_id.ok()) return source_id.status();
  store::ScanInfo info;
  info.name = input.name.empty() ? absl::StrCat("backproject-", *batch) : input.name;
  absl::StatusOr<bool> exists = store.HasScan(info.name);
  if (!exists.ok()) return exists.status();
  if (*exists) {
    return absl::AlreadyExistsError(absl::StrCat("project '", store.name(),
                                                 "' already has a scan or batch '", info.name, "'"));
  }
  info.rig = "derived";
  info.pose = input.pose;
  info.batch = *batch;
  if (absl::Status stop = clock.Start("store image", 0.1); !stop.ok()) return stop;
  absl::StatusOr<std::string> blob = store.PutBlob(input.image);
  if (!blob.ok()) return blob.status();
  store::SourceInfo src;
  src.id = *source_id;
  src.name = "image";
  src.modality = records::Modality::kDerived;
  src.pose = input.pose;
  src.blob_sha256 = *blob;
  src.width_px = decoded->width_px;
  src.height_px = decoded->height_px;
  src.camera = DerivedCameraText(input.pinhole, input.intrinsics, input.render_id);
  info.sources.push_back(src);
  ingest::DerivedSource image;
  image.pose = input.pose;
  image.pinhole = input.pinhole;
  image.intrinsics = input.intrinsics;
  image.image = std::move(*decoded);
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
                          /*max_image_pixels=*/0, /*images=*/nullptr, plan, result, clock);
  if (!next.ok()) return next.status();
  if (result.pixels_back_projected == 0) {
    if (result.pixels_invalid > 0 && result.pixels_outside == 0) {
      return absl::InvalidArgumentError(absl::StrCat(
          "no pixel of the image has a usable colour: all ", result.pixels_invalid,
          " pixels with a depth have R, G or B NaN or infinite"));
    }
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

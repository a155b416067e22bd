// The rebuild flow (flows.h): the whole project recomputed from its raw blobs. The oracle the
// incremental flows are tested against, and the way back from any doubt about derived data.
#include "absl/strings/str_cat.h"
#include "lattice/flows/change.h"
#include "lattice/flows/flows.h"
#include "lattice/fusion/fuse.h"
#include "lattice/ingest/sample.h"
#include "lattice/ingest/voxelise.h"

namespace vasl::flows {

absl::StatusOr<FlowResult> Rebuild(store::ProjectStore& store, int64_t max_image_pixels,
                                   const StageFn& stage) {
  FlowResult result;
  internal::StageClock clock(result, stage);
  const double h = store.settings().vossel_size_m;
  absl::StatusOr<std::vector<store::ScanInfo>> scans = store.ListScans();
  if (!scans.ok()) return scans.status();
  if (store.head_version() == 0 || scans->empty()) {
    return absl::FailedPreconditionError(
        absl::StrCat("project '", store.name(), "' has no scans to rebuild"));
  }
  const std::vector<internal::SourceRef> sources = internal::SourcesOf(*scans);

  // §1: every LiDAR binned and merged in source-id order, one in memory at a time.
  store::Snapshot next;
  next.tile_vossels = store.settings().tile_vossels;
  next.geometry = ingest::EmptyGeometry(h);
  double fraction = 0.05;
  for (const internal::SourceRef& src : sources) {
    if (!src.lidar()) continue;
    if (absl::Status stop = clock.Start(absl::StrCat("voxelise source ", src.info.id), fraction);
        !stop.ok()) {
      return stop;
    }
    absl::StatusOr<ingest::LidarSource> lidar = LoadLidar(store, src.info, src.batch);
    if (!lidar.ok()) return lidar.status();
    absl::StatusOr<ingest::BinnedLidar> binned = ingest::BinLidar(*lidar, h);
    if (!binned.ok()) return binned.status();
    ingest::MergeBinned(next.geometry, *binned);
  }
  if (absl::Status stop = clock.Start("normals", 0.3); !stop.ok()) return stop;
  ingest::DeriveCentroidAndCovariance(next.geometry);
  ingest::ComputeNormals(next.geometry);

  // §3-§6: every source on every tile.
  const double span = 0.5 / double(sources.size());
  fraction = 0.35;
  for (const internal::SourceRef& src : sources) {
    if (absl::Status stop = clock.Start(absl::StrCat("records of source ", src.info.id), fraction);
        !stop.ok()) {
      return stop;
    }
    fraction += span;
    absl::StatusOr<ingest::SourceRecords> recs =
        internal::StoredSourceRecords(store, src, next.geometry, max_image_pixels);
    if (!recs.ok()) return recs.status();
    next.records.Append(recs->records);
    if (!src.derived()) next.reach[src.info.id] = std::move(recs->reach);
    ++result.sources_computed;
  }
  next.records.SortByVossel();
  if (absl::Status stop = clock.Start("fuse", 0.85); !stop.ok()) return stop;
  store::Manifest head_manifest;  // the profiles whose layers HEAD keeps stay kept
  if (store.head_version() > 0) {
    absl::StatusOr<store::Manifest> m = store.LoadManifest(store.head_version());
    if (!m.ok()) return m.status();
    head_manifest = std::move(*m);
  }
  if (absl::Status s = internal::FuseAll(store, head_manifest, next); !s.ok()) return s;

  store::CommitPlan plan;
  plan.made_by = "rebuild";
  plan.replace_all = true;
  if (absl::Status s = internal::CommitFlow(store, std::move(next), plan, result, clock); !s.ok()) {
    return s;
  }
  return result;
}

}  // namespace vasl::flows

/// @file engine_impl.h
/// @brief The engine's state behind its facade (engine.cc, which alone includes this): the open
///        projects, each with its store, writer lock and cached HEAD snapshot; the image caches
///        renders and revisits share; and how a committing flow publishes its snapshot as HEAD.
#pragma once

#include <chrono>
#include <filesystem>
#include <map>
#include <memory>
#include <mutex>
#include <string>

#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "lattice/engine.h"
#include "lattice/operations.h"
#include "lattice/flows/flows.h"
#include "lattice/flows/tile_budget.h"
#include "lattice/ingest/validate.h"

namespace vasl {
namespace engine_internal {

using Clock = std::chrono::steady_clock;
inline double SecondsSince(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

}  // namespace engine_internal

struct Engine::Impl {
  using Clock = engine_internal::Clock;

  struct Project {
    std::unique_ptr<store::ProjectStore> store;
    std::mutex write_mu;  ///< one writer per project
    std::mutex head_mu;   ///< guards `head`
    std::shared_ptr<const store::Snapshot> head;
    flows::FusedLayerCache fused_layers;  ///< other profiles' fused values, read from tiles
  };

  std::filesystem::path data_dir;
  EngineLimits limits;
  /// Decoded camera images of colour-detail renders (§8), shared by the projects.
  std::unique_ptr<flows::SourceImageCache> detail_images;
  /// Older cameras' decoded images and older LiDARs' points that revisits read
  /// (EngineLimits::max_revisit_image_bytes).
  std::unique_ptr<flows::SourceImageCache> revisit_images;
  std::mutex mu;  ///< guards `projects`
  std::map<std::string, std::shared_ptr<Project>> projects;

  absl::StatusOr<std::shared_ptr<Project>> Find(const std::string& name) {
    if (absl::Status s = store::ValidateProjectName(name); !s.ok()) return s;
    std::lock_guard<std::mutex> lock(mu);
    auto it = projects.find(name);
    if (it != projects.end()) return it->second;
    const std::filesystem::path dir = data_dir / name;
    if (!std::filesystem::exists(dir / "catalog.sqlite")) {
      return absl::NotFoundError(absl::StrCat("project '", name, "' does not exist"));
    }
    auto store = store::ProjectStore::Open(dir);
    if (!store.ok()) return store.status();
    auto p = std::make_shared<Project>();
    p->store = std::move(*store);
    projects[name] = p;
    return p;
  }

  absl::StatusOr<std::shared_ptr<const store::Snapshot>> Snapshot(Project& p, int64_t version) {
    const int64_t head = p.store->head_version();
    if (version == 0 || version == head) {
      std::lock_guard<std::mutex> lock(p.head_mu);
      if (!p.head || p.head->version != head) {
        auto snap = p.store->LoadSnapshot(head);
        if (!snap.ok()) return snap.status();
        p.head = *snap;
      }
      return p.head;
    }
    if (version < 0 || version > head) {
      return absl::NotFoundError(absl::StrCat("project '", p.store->name(), "' has no version ",
                                              version, " (HEAD is ", head, ")"));
    }
    return p.store->LoadSnapshot(version);
  }

  /// What a reader (render, records query) takes of version `version` (0: HEAD) whole: HEAD
  /// when cached, else the version loaded whole when it fits max_snapshot_bytes (HEAD is then
  /// cached); null when it does not, and the reader goes tile group by tile group.
  absl::StatusOr<std::shared_ptr<const store::Snapshot>> Whole(Project& p, int64_t version) {
    const int64_t head = p.store->head_version();
    if (version == 0 || version == head) {
      std::lock_guard<std::mutex> lock(p.head_mu);
      if (p.head && p.head->version == head) return p.head;
    }
    if (version < 0 || version > head || head == 0) {
      return Snapshot(p, version);  // its NOT_FOUND, or the empty project
    }
    auto manifest = p.store->LoadManifest(version == 0 ? head : version);
    if (!manifest.ok()) return manifest.status();
    if (flows::VersionMemoryBytes(*manifest, /*with_records=*/true, 1) >
        limits.max_snapshot_bytes) {
      return std::shared_ptr<const store::Snapshot>();
    }
    return Snapshot(p, version);
  }

  /// HEAD as an ingest, a back-projection or a deletion reads it: whole (and cached) while it
  /// fits max_snapshot_bytes; beyond it without records, which the change then reads for the
  /// tiles it rewrites only (flows::internal::Propagate), so that it holds the project's
  /// geometry and those tiles.
  absl::StatusOr<std::shared_ptr<const store::Snapshot>> IngestHead(Project& p) {
    auto whole = Whole(p, 0);
    if (!whole.ok() || *whole) return whole;
    return p.store->LoadSnapshot(p.store->head_version(), {}, /*with_records=*/false);
  }

  absl::StatusOr<ProjectInfo> Info(Project& p) {
    ProjectInfo info;
    info.name = p.store->name();
    info.description = p.store->settings().description;
    info.vossel_size_m = p.store->settings().vossel_size_m;
    info.created_utc = p.store->created_utc();
    info.origin_m = p.store->origin();
    auto head = p.store->HeadInfo();
    if (!head.ok()) return head.status();
    info.head_version = head->version;
    info.vossel_count = head->vossel_count;
    info.record_count = head->record_count;
    auto scans = p.store->ListScans();
    if (!scans.ok()) return scans.status();
    info.scan_count = int64_t(scans->size());
    return info;
  }

  // Publishes a flow's committed snapshot as HEAD and fills the caller's result.
  IngestResult Finish(Project& p, flows::FlowResult flow, Clock::time_point t0, IngestResult result) {
    const int64_t vossels_before = result.new_vossels;  // RunFlow: HEAD's before the flow
    {  // HEAD stays cached while it fits the budget; beyond it readers go by tile groups
      std::lock_guard<std::mutex> lock(p.head_mu);
      const bool fits = !flow.snapshot->records_partial &&
                        flows::VersionMemoryBytes(flow.snapshot->manifest, true, 1) <=
                            limits.max_snapshot_bytes;
      p.head = fits ? flow.snapshot : nullptr;
    }
    for (auto& stage : flow.stage_seconds) result.stage_seconds.push_back(std::move(stage));
    result.version = flow.version;
    result.vossel_count = int64_t(flow.snapshot->geometry.size());
    result.record_count = int64_t(flow.snapshot->records.size());
    if (flow.snapshot->records_partial) {  // it holds the records of the tiles it rewrote
      auto info = p.store->HeadInfo();
      if (info.ok()) result.record_count = info->record_count;
    }
    result.new_vossels = result.vossel_count - vossels_before;
    result.sources_computed = flow.sources_computed;
    result.sources_revisited = flow.sources_revisited;
    result.pairs_revisited = flow.pairs_revisited;
    result.blocks_revisited = flow.blocks_revisited;
    result.vossels_revisited = flow.vossels_revisited;
    result.vossels_in_blocks = flow.vossels_in_blocks;
    result.sources_refreshed = flow.sources_refreshed;
    result.tiles_changed = flow.tiles_changed;
    result.records_computed = flow.records_computed;
    result.records_rewritten = flow.records_rewritten;
    result.commit_times = flow.commit_times;
    result.bytes_written = flow.bytes_written;
    result.pixels_back_projected = flow.pixels_back_projected;
    result.pixels_outside = flow.pixels_outside;
    result.pixels_invalid = flow.pixels_invalid;
    result.calibration = std::move(flow.calibration);
    result.seconds = engine_internal::SecondsSince(t0);
    return result;
  }

  /// Finish for a flow that added a scan (ingest, back-projection): also its catalog id.
  IngestResult FinishAdded(Project& p, flows::FlowResult flow, Clock::time_point t0,
                           IngestResult result) {
    IngestResult done = Finish(p, std::move(flow), t0, std::move(result));
    auto scans = p.store->ListScans();
    if (scans.ok() && !scans->empty()) done.scan_id = scans->back().id;
    return done;
  }

  /// Runs a committing flow (`flow(project)`) under the project's writer lock and publishes
  /// its snapshot as HEAD; `added`: the flow added a scan (FinishAdded); `op`: the request it
  /// runs under (Replay first, then recorded by the commit); `t0`: when the caller's work began.
  template <typename Flow>
  absl::StatusOr<IngestResult> RunFlow(const std::string& project, bool added,
                                       const store::OperationRecord& op, Flow flow,
                                       Clock::time_point t0 = Clock::now()) {
    auto found = Find(project);
    if (!found.ok()) return found.status();
    Project& p = **found;
    std::lock_guard<std::mutex> writer(p.write_mu);
    absl::StatusOr<std::optional<IngestResult>> replayed = ReplayOperation(*p.store, op);
    if (!replayed.ok()) return replayed.status();
    if (*replayed) return std::move(**replayed);
    store::OperationScope scope(*p.store, op);
    IngestResult result;  // its new_vossels holds HEAD's vossels until Finish
    if (auto before = p.store->HeadInfo(); before.ok()) result.new_vossels = before->vossel_count;
    absl::StatusOr<flows::FlowResult> done = flow(p);
    if (!done.ok()) return CollectAfterFailure(p, done.status());
    return added ? FinishAdded(p, std::move(*done), t0, std::move(result))
                 : Finish(p, std::move(*done), t0, std::move(result));
  }

  /// A failed change may have stored blobs or objects that no version names (a rejected scan's
  /// images): they go now, not at the next commit, so that repeating a bad request cannot fill
  /// the disk. Call with the writer lock held. Returns `failure`.
  static absl::Status CollectAfterFailure(Project& p, absl::Status failure) {
    (void)p.store->CollectGarbage();  // best effort: the next commit or open collects again
    return failure;
  }

  /// Profile `name` (empty: the project's active one) at `revision` (0: latest).
  absl::StatusOr<reweight::NamedProfile> Profile(Project& p, const std::string& name,
                                                 int32_t revision) {
    std::string resolved = name;
    if (resolved.empty()) {
      absl::StatusOr<std::string> active = p.store->ActiveProfile();
      if (!active.ok()) return active.status();
      resolved = *active;
    }
    return reweight::LoadProfile(*p.store, resolved, revision);
  }

  /// What a flow that derives a profile from HEAD's records reads (normalisation, lens maps):
  /// the store, HEAD and base profile `base` (empty: active). FAILED_PRECONDITION before the
  /// first version.
  struct HeadAndBase {
    store::ProjectStore* store = nullptr;
    std::shared_ptr<const store::Snapshot> head;
    fusion::WeightingProfile base;
  };
  absl::StatusOr<HeadAndBase> HeadUnder(const std::string& project, const std::string& base) {
    auto p = Find(project);
    if (!p.ok()) return p.status();
    if ((*p)->store->head_version() == 0) {
      return absl::FailedPreconditionError(
          absl::StrCat("project '", project, "' has no version yet"));
    }
    auto profile = Profile(**p, base, 0);
    if (!profile.ok()) return profile.status();
    auto snap = Snapshot(**p, 0);
    if (!snap.ok()) return snap.status();
    return HeadAndBase{(*p)->store.get(), std::move(*snap), std::move(profile->profile)};
  }

  ingest::ScanLimits ScanLimits() const {
    return {limits.max_points_per_scan, limits.max_panoramas_per_scan, limits.max_image_bytes,
            limits.max_image_pixels};
  }
};

}  // namespace vasl

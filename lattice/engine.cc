#include "lattice/engine.h"
#include "lattice/engine_impl.h"
#include "lattice/operations.h"

#include <algorithm>
#include <chrono>
#include <mutex>

#include "absl/strings/str_cat.h"
#include "lattice/flows/flows.h"
#include "lattice/flows/world_frame.h"
#include "lattice/fusion/fuse.h"
#include "lattice/ingest/sources.h"
#include "lattice/ingest/validate.h"

namespace vasl {
namespace fs = std::filesystem;
namespace {

using engine_internal::Clock;
using engine_internal::SecondsSince;

// A flow's stage reports as the caller's progress (may be empty).
flows::StageFn StageReporter(const ProgressFn& progress) {
  return [&progress](const std::string& stage, double fraction) {
    return progress ? progress({stage, fraction}) : absl::OkStatus();
  };
}

}  // namespace

// Engine::Impl: lattice/engine_impl.h.

Engine::Engine(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
Engine::~Engine() = default;

absl::StatusOr<std::unique_ptr<Engine>> Engine::Open(const fs::path& data_dir,
                                                     const EngineLimits& limits) {
  std::error_code ec;
  fs::create_directories(data_dir, ec);
  if (ec) {
    return absl::FailedPreconditionError(
        absl::StrCat("cannot create data directory ", data_dir.string(), ": ", ec.message()));
  }
  auto impl = std::make_unique<Impl>();
  impl->data_dir = data_dir;
  impl->limits = limits;
  impl->detail_images = std::make_unique<flows::SourceImageCache>(limits.max_detail_image_bytes);
  impl->revisit_images =
      std::make_unique<flows::SourceImageCache>(limits.max_revisit_image_bytes);
  return std::unique_ptr<Engine>(new Engine(std::move(impl)));
}

const EngineLimits& Engine::limits() const { return impl_->limits; }

absl::StatusOr<ProjectInfo> Engine::CreateProject(const std::string& name,
                                                  const store::ProjectSettings& settings) {
  if (absl::Status s = store::ValidateProjectName(name); !s.ok()) return s;
  if (!(settings.vossel_size_m >= 1e-3 && settings.vossel_size_m <= 10.0)) {
    return absl::InvalidArgumentError("vossel_size_m must lie in [0.001, 10] metres");
  }
  if (settings.keep_versions < 0) return absl::InvalidArgumentError("keep_versions must be ≥ 0");
  std::shared_ptr<Impl::Project> p;
  {
    std::lock_guard<std::mutex> lock(impl_->mu);
    const fs::path dir = impl_->data_dir / name;
    if (impl_->projects.count(name) || fs::exists(dir)) {
      return absl::AlreadyExistsError(absl::StrCat("project '", name, "' already exists"));
    }
    auto store = store::ProjectStore::Create(dir, name, settings);
    if (!store.ok()) return store.status();
    p = std::make_shared<Impl::Project>();
    p->store = std::move(*store);
    impl_->projects[name] = p;
  }
  return impl_->Info(*p);
}

absl::StatusOr<ProjectInfo> Engine::GetProject(const std::string& name) {
  auto p = impl_->Find(name);
  if (!p.ok()) return p.status();
  return impl_->Info(**p);
}

absl::StatusOr<std::vector<ProjectInfo>> Engine::ListProjects() {
  std::vector<std::string> names;
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator(impl_->data_dir, ec)) {
    if (entry.is_directory() && fs::exists(entry.path() / "catalog.sqlite")) {
      names.push_back(entry.path().filename().string());
    }
  }
  if (ec) return absl::InternalError(absl::StrCat("cannot list ", impl_->data_dir.string(), ": ", ec.message()));
  std::sort(names.begin(), names.end());
  std::vector<ProjectInfo> out;
  for (const std::string& name : names) {
    if (!store::ValidateProjectName(name).ok()) continue;  // not one of ours
    auto info = GetProject(name);
    if (!info.ok()) {  // a damaged project is reported, and does not hide the others
      ProjectInfo damaged;
      damaged.name = name;
      damaged.problem = std::string(info.status().message());
      out.push_back(std::move(damaged));
      continue;
    }
    out.push_back(std::move(*info));
  }
  return out;
}

absl::StatusOr<std::vector<store::ScanInfo>> Engine::ListScans(const std::string& project) {
  auto p = impl_->Find(project);
  if (!p.ok()) return p.status();
  auto scans = (*p)->store->ListScans();
  if (!scans.ok()) return scans.status();
  const Eigen::Vector3d origin = (*p)->store->origin().value_or(Eigen::Vector3d::Zero());
  for (store::ScanInfo& scan : *scans) flows::ShiftScan(scan, origin);  // §1: world out
  return scans;
}

absl::StatusOr<std::pair<store::VisualReferenceInfo, std::string>> Engine::GetVisualReference(
    const std::string& project, const std::string& scan, const std::string& name) {
  auto p = impl_->Find(project);
  if (!p.ok()) return p.status();
  auto scans = ListScans(project);  // world poses
  if (!scans.ok()) return scans.status();
  return flows::VisualReference(*(*p)->store, *scans, project, scan, name);
}

absl::StatusOr<std::vector<flows::SourceConfidence>> Engine::ScanConfidence(
    const std::string& project, const std::string& scan) {
  auto p = impl_->Find(project);
  if (!p.ok()) return p.status();
  auto scans = (*p)->store->ListScans();
  if (!scans.ok()) return scans.status();
  return flows::ScanConfidence(*(*p)->store, *scans, project, scan, impl_->limits.max_image_pixels);
}

absl::StatusOr<IngestResult> Engine::IngestScan(const std::string& project, const ScanInput& scan,
                                                const ProgressFn& progress) {
  const auto t0 = Clock::now();
  std::vector<std::pair<std::string, double>> stages;  // before the flow's own
  auto stage_clock = Clock::now();
  const auto stage_done = [&](const char* stage, double fraction) {
    stages.emplace_back(stage, SecondsSince(stage_clock));
    stage_clock = Clock::now();
    return progress ? progress({stage, fraction}) : absl::OkStatus();
  };
  // An unknown project is named before any image is read; the panoramas' headers are read
  // here, their pixels one at a time as the flow samples each camera.
  if (auto found = impl_->Find(project); !found.ok()) return found.status();
  auto images = ingest::ValidateScan(scan, impl_->ScanLimits());
  if (!images.ok()) return images.status();

  const store::OperationRecord op{scan.request_id, "ingest", scan.scan_name};
  return impl_->RunFlow(project, true, op, [&](Impl::Project& p) -> absl::StatusOr<flows::FlowResult> {
    store::ProjectStore& st = *p.store;
    auto exists = st.HasScan(scan.scan_name);
    if (!exists.ok()) return exists.status();
    if (*exists) {
      return absl::AlreadyExistsError(absl::StrCat("project '", project, "' already has a scan '",
                                                   scan.scan_name, "'"));
    }
    if (absl::Status stop = stage_done("validate", 0.05); !stop.ok()) return stop;

    auto head = impl_->IngestHead(p);
    if (!head.ok()) return head.status();
    if (scan.lidar.xyz_sensor_m.empty() && (*head)->geometry.size() == 0) {
      return flows::CameraOnlyWithoutGeometry(project, scan.scan_name);
    }
    // §1: the first scan fixes a missing origin (in its commit); the flow works beneath it.
    std::optional<Eigen::Vector3d> origin = st.origin();
    if (!origin) {
      origin = flows::OriginOfFirstScan(scan);
      st.ProposeOrigin(*origin);
    }
    const double h = st.settings().vossel_size_m;
    if (auto s = flows::CheckScanWithinReach(scan, *origin, h); !s.ok()) return s;
    // Raw inputs, content-addressed (ARCHITECTURE.md: blobs/).
    auto info = flows::StoreScanBlobs(st, scan, *images);
    if (!info.ok()) return info.status();
    flows::ShiftScan(*info, -*origin);
    if (absl::Status stop = stage_done("store blobs", 0.15); !stop.ok()) return stop;
    auto flow = flows::IngestScan(st, **head, *info, scan, impl_->limits.max_image_pixels,
                                  StageReporter(progress), impl_->revisit_images.get());
    if (flow.ok()) flow->stage_seconds.insert(flow->stage_seconds.begin(), stages.begin(), stages.end());
    return flow;
  }, t0);
}

absl::StatusOr<IngestResult> Engine::BackProject(const std::string& project,
                                                 BackProjectInput input,
                                                 const ProgressFn& progress) {
  // On failure a stored image is collected at once (RunFlow).
  const store::OperationRecord op{input.request_id, "back-project", input.name};
  return impl_->RunFlow(project, true, op, [&](Impl::Project& p) -> absl::StatusOr<flows::FlowResult> {
    auto head = impl_->IngestHead(p);  // its derived records join as a scan's do
    if (!head.ok()) return head.status();
    const Eigen::Vector3d origin = p.store->origin().value_or(Eigen::Vector3d::Zero());
    if (auto s = flows::CheckWithinReach(input.pose.o_world, origin,
                                         p.store->settings().vossel_size_m, "the image's pose");
        !s.ok()) {
      return s;
    }
    input.pose = flows::Shifted(input.pose, -origin);  // §1: the lattice's frame
    return flows::BackProject(*p.store, **head, input, impl_->limits.max_image_bytes,
                              impl_->limits.max_image_pixels, StageReporter(progress));
  });
}

absl::StatusOr<IngestResult> Engine::Rebuild(const std::string& project, const ProgressFn& progress,
                                             const std::string& request_id) {
  const store::OperationRecord op{request_id, "rebuild", ""};
  return impl_->RunFlow(project, false, op, [&](Impl::Project& p) {
    return flows::Rebuild(*p.store, impl_->limits.max_image_pixels,
                          impl_->limits.max_snapshot_bytes, StageReporter(progress));
  });
}

absl::StatusOr<IngestResult> Engine::DeleteScan(const std::string& project, const std::string& scan,
                                                const ProgressFn& progress,
                                                const std::string& request_id) {
  const store::OperationRecord op{request_id, "delete", scan};
  return impl_->RunFlow(project, false, op, [&](Impl::Project& p) -> absl::StatusOr<flows::FlowResult> {
    auto head = impl_->IngestHead(p);  // as an ingest reads it: see Impl::IngestHead
    if (!head.ok()) return head.status();
    return flows::DeleteScan(*p.store, **head, scan, impl_->limits.max_image_pixels,
                             StageReporter(progress), impl_->revisit_images.get());
  });
}

absl::StatusOr<std::optional<store::OperationRecord>> Engine::FindOperation(
    const std::string& project, const store::OperationRecord& asked) {
  auto p = impl_->Find(project);
  if (!p.ok()) return p.status();
  return FindCommitted(*(*p)->store, asked);
}

absl::Status Engine::SetOperationAnswer(const std::string& project, const std::string& request_id,
                                        const std::string& answer) {
  auto p = impl_->Find(project);
  if (!p.ok()) return p.status();
  return (*p)->store->SetOperationAnswer(request_id, answer);
}

absl::StatusOr<std::vector<store::VersionInfo>> Engine::ListVersions(const std::string& project) {
  auto p = impl_->Find(project);
  if (!p.ok()) return p.status();
  return (*p)->store->ListVersions();
}

absl::StatusOr<flows::ExportResult> Engine::Export(const std::string& project, int64_t version,
                                                   const fs::path& path) {
  auto p = impl_->Find(project);
  if (!p.ok()) return p.status();
  if ((*p)->store->head_version() == 0) {
    return absl::FailedPreconditionError(
        absl::StrCat("project '", project, "' has no version yet: ingest a scan first"));
  }
  auto snap = impl_->Snapshot(**p, version);
  if (!snap.ok()) return snap.status();
  return flows::Export(**snap, (*p)->store->origin().value_or(Eigen::Vector3d::Zero()), path);
}

absl::StatusOr<RenderImage> Engine::Render(const std::string& project, const RenderRequest& request) {
  auto p = impl_->Find(project);
  if (!p.ok()) return p.status();
  if (request.width_px <= 0 || request.height_px <= 0) {
    return absl::InvalidArgumentError("render width_px and height_px must be positive");
  }
  if (request.width_px > impl_->limits.max_render_width_px ||
      request.height_px > impl_->limits.max_render_height_px) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "render of ", request.width_px, "x", request.height_px, " exceeds the limit of ",
        impl_->limits.max_render_width_px, "x", impl_->limits.max_render_height_px));
  }
  if (absl::Status s = ingest::ValidatePose(request.pose, "render"); !s.ok()) return s;
  if ((*p)->store->head_version() == 0) {
    return absl::FailedPreconditionError(
        absl::StrCat("project '", project, "' has no scans yet: ingest one before rendering"));
  }
  auto profile = impl_->Profile(**p, request.profile, request.profile_revision);
  if (!profile.ok()) return profile.status();
  auto snap = impl_->Whole(**p, request.version);
  if (!snap.ok()) return snap.status();
  const Eigen::Vector3d origin = (*p)->store->origin().value_or(Eigen::Vector3d::Zero());
  if (auto s = flows::CheckWithinReach(request.pose.o_world, origin,
                                       (*p)->store->settings().vossel_size_m, "the render's pose");
      !s.ok()) {
    return s;
  }
  RenderRequest local = request;  // §1: the lattice's frame
  local.pose = flows::Shifted(request.pose, -origin);
  flows::RenderCaches caches;
  caches.fused = &(*p)->fused_layers;
  caches.images = impl_->detail_images.get();
  caches.max_image_pixels = impl_->limits.max_image_pixels;
  if (*snap) return flows::RenderQuery(*(*p)->store, *snap, profile->profile, local, caches);
  const int64_t version = request.version == 0 ? (*p)->store->head_version() : request.version;
  return flows::RenderQueryInTiles(*(*p)->store, version, profile->profile, local, caches,
                                   impl_->limits.max_snapshot_bytes);
}

absl::StatusOr<reweight::NamedProfile> Engine::CreateProfile(
    const std::string& project, const fusion::WeightingProfile& profile) {
  auto p = impl_->Find(project);
  if (!p.ok()) return p.status();
  if (auto s = ingest::ValidateText("the profile name", profile.name, 128); !s.ok()) return s;
  return reweight::CreateProfile(*(*p)->store, profile);
}

absl::StatusOr<std::vector<reweight::NamedProfile>> Engine::ListProfiles(
    const std::string& project, std::string* active) {
  auto p = impl_->Find(project);
  if (!p.ok()) return p.status();
  auto a = (*p)->store->ActiveProfile();
  if (!a.ok()) return a.status();
  if (active != nullptr) *active = *a;
  return reweight::ListProfiles(*(*p)->store);
}

absl::StatusOr<reweight::NamedProfile> Engine::GetProfile(const std::string& project,
                                                          const std::string& name,
                                                          int32_t revision) {
  auto p = impl_->Find(project);
  if (!p.ok()) return p.status();
  return impl_->Profile(**p, name, revision);
}

absl::Status Engine::SetActiveProfile(const std::string& project, const std::string& name) {
  auto p = impl_->Find(project);
  if (!p.ok()) return p.status();
  return (*p)->store->SetActiveProfile(name);
}

absl::StatusOr<reweight::ReweightResult> Engine::Reweight(const std::string& project,
                                                          const std::string& name,
                                                          int32_t revision,
                                                          const ProgressFn& progress,
                                                          const std::string& request_id) {
  auto found = impl_->Find(project);
  if (!found.ok()) return found.status();
  Impl::Project& p = **found;
  auto profile = impl_->Profile(p, name, revision);
  if (!profile.ok()) return profile.status();
  const store::OperationRecord op{request_id, "reweight", ReweightSubject(name, revision)};
  std::lock_guard<std::mutex> writer(p.write_mu);
  absl::StatusOr<std::optional<reweight::ReweightResult>> replayed = ReplayReweight(*p.store, op);
  if (!replayed.ok()) return replayed.status();
  if (*replayed) return std::move(**replayed);
  store::OperationScope scope(*p.store, op);
  auto result = reweight::Reweight(*p.store, profile->profile, [&](int64_t done, int64_t total) {
    return progress ? progress({absl::StrCat("fused tile ", done, " of ", total),
                                double(done) / double(total)})
                    : absl::OkStatus();
  });
  if (!result.ok()) return Impl::CollectAfterFailure(p, result.status());
  if (!result->unchanged) {  // HEAD keeps its arrays; only its manifest gained a layer
    std::lock_guard<std::mutex> lock(p.head_mu);
    if (p.head) {
      auto manifest = p.store->LoadManifest(result->version);
      if (!manifest.ok()) return manifest.status();
      // HEAD's arrays move into the new snapshot when no reader holds it (every copy of
      // p.head is taken under head_mu, held here; LoadSnapshot and CommitFlow make it a
      // non-const object); while a reader holds it, it is copied.
      auto next = p.head.use_count() == 1
          ? std::make_shared<store::Snapshot>(std::move(const_cast<store::Snapshot&>(*p.head)))
          : std::make_shared<store::Snapshot>(*p.head);
      next->version = result->version;
      next->manifest = std::move(*manifest);
      p.head = std::move(next);
    }
  }
  return result;
}

absl::StatusOr<reweight::NormaliseOutcome> Engine::Normalise(const std::string& project,
                                                             const std::string& base,
                                                             const std::string& name) {
  auto in = impl_->HeadUnder(project, base);
  if (!in.ok()) return in.status();
  return reweight::NormaliseProfile(*in->store, *in->head, in->base, name);
}

absl::StatusOr<reweight::LensOutcome> Engine::EstimateLens(const std::string& project,
                                                           const std::string& base,
                                                           const reweight::LensRequest& request) {
  auto in = impl_->HeadUnder(project, base);
  if (!in.ok()) return in.status();
  return reweight::EstimateLensProfile(*in->store, *in->head, in->base, request);
}

absl::StatusOr<std::vector<fusion::LensMap>> Engine::ListLensMaps(const std::string& project) {
  auto p = impl_->Find(project);
  if (!p.ok()) return p.status();
  return reweight::ListLensMaps(*(*p)->store);
}

absl::StatusOr<flows::RecordsQueryResult> Engine::QueryRecords(
    const std::string& project, int64_t version, const Eigen::Vector3d& min_m,
    const Eigen::Vector3d& max_m, const std::string& profile_name, int64_t limit) {
  auto p = impl_->Find(project);
  if (!p.ok()) return p.status();
  if ((*p)->store->head_version() == 0) {
    return absl::FailedPreconditionError(absl::StrCat("project '", project, "' has no version yet"));
  }
  auto profile = impl_->Profile(**p, profile_name, 0);
  if (!profile.ok()) return profile.status();
  auto snap = impl_->Whole(**p, version);
  if (!snap.ok()) return snap.status();
  const Eigen::Vector3d origin = (*p)->store->origin().value_or(Eigen::Vector3d::Zero());
  auto found =
      *snap ? flows::QueryRecords(*(*p)->store, **snap, min_m - origin, max_m - origin,
                                  profile->profile, limit)
            : flows::QueryRecordsInTiles(*(*p)->store,
                                         version == 0 ? (*p)->store->head_version() : version,
                                         min_m - origin, max_m - origin, profile->profile,
                                         limit, impl_->limits.max_snapshot_bytes);
  if (!found.ok()) return found.status();
  for (flows::RecordRow& row : found->rows) row.centroid_m += origin;  // §1: world out
  return found;
}

absl::StatusOr<IngestResult> Engine::Rollback(const std::string& project, int64_t version,
                                              const ProgressFn& progress) {
  return impl_->RunFlow(project, false, store::OperationRecord{}, [&](Impl::Project& p) {
    return flows::Rollback(*p.store, version, StageReporter(progress));
  });
}

absl::Status Engine::SetPinned(const std::string& project, int64_t version, bool pinned) {
  auto p = impl_->Find(project);
  if (!p.ok()) return p.status();
  return (*p)->store->SetPinned(version, pinned);
}

absl::StatusOr<RecordsInspection> Engine::InspectRecords(const std::string& project,
                                                        int64_t version) {
  auto p = impl_->Find(project);
  if (!p.ok()) return p.status();
  const int64_t head = (*p)->store->head_version();
  if (head == 0) {
    return absl::FailedPreconditionError(absl::StrCat("project '", project, "' has no version yet"));
  }
  RecordsInspection out;
  out.version = version == 0 ? head : version;
  auto manifest = (*p)->store->LoadManifest(out.version);
  if (!manifest.ok()) return manifest.status();
  out.tile_count = int64_t(manifest->tiles.size());
  for (const auto& [key, layers] : manifest->tiles) {
    auto it = layers.find(store::kLayerRecords);
    if (it != layers.end()) out.record_count += it->second.records;
  }
  auto attributes = (*p)->store->InspectRecords(out.version);
  if (!attributes.ok()) return attributes.status();
  out.attributes = std::move(*attributes);
  return out;
}

}  // namespace vasl

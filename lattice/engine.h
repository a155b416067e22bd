/// @file engine.h
/// @brief The typed facade of libvasl that the server (and tests) call: projects, ingest,
///        render, inspection. It orchestrates the flows of ARCHITECTURE.md ("The main flows")
///        over store/, ingest/, fusion/ and render/. No gRPC or protobuf types here.
/// @details Every position the facade takes or gives is in world coordinates; beneath the
///          project's origin (VASL-MODEL §1, flows/world_frame.h) the flows work in the
///          lattice's. Errors are absl::Status with messages a user can act on:
///          INVALID_ARGUMENT for bad input, NOT_FOUND for an unknown project or version,
///          ALREADY_EXISTS for a duplicate project or scan name, RESOURCE_EXHAUSTED for limits,
///          INTERNAL only for bugs. Bad input never changes a project.
/// @warning Thread-safe: any number of concurrent renders and reads; ingests into one project
///          are serialised (one writer per project), ingests into different projects run in
///          parallel.
#pragma once

#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "lattice/flows/flows.h"
#include "lattice/geometry/pose.h"
#include "lattice/ingest/scan_input.h"
#include "lattice/records/records.h"
#include "lattice/render/render.h"
#include "lattice/reweight/lens_flow.h"
#include "lattice/reweight/normalise_flow.h"
#include "lattice/reweight/profiles.h"
#include "lattice/reweight/reweight_flow.h"
#include "lattice/store/project_store.h"

namespace vasl {

/// Limits on what a client controls (ARCHITECTURE.md "Errors and limits").
struct EngineLimits {
  int64_t max_points_per_scan = 50'000'000;
  int64_t max_panoramas_per_scan = 16;
  int64_t max_image_bytes = 512ll << 20;     ///< one encoded image
  int64_t max_image_pixels = 16384ll * 8192;  ///< one decoded image
  int max_render_width_px = 16384;
  int max_render_height_px = 8192;
  /// Decoded camera images that renders with colour detail (§8) keep and read at once
  /// (float RGB: 400 MB for an 8192×4096 panorama); cameras beyond it keep their records' colour.
  int64_t max_detail_image_bytes = 2ll << 30;
  /// What a render or a records query holds of a version at once, estimated from its tiles'
  /// counts (flows::TileMemoryBytes). A version within it is read whole (HEAD stays cached
  /// while it fits); a larger one is read tile group by tile group within it, so that a
  /// project larger than memory still renders and answers queries. An ingest then reads the
  /// records of the tiles it rewrites alone, and a rebuild makes its tiles group by group.
  int64_t max_snapshot_bytes = 4ll << 30;
  /// Decoded images (with their artefact maps and channel shift corrected, §9) of the older
  /// cameras, and points (with their gap fill) of the older LiDARs, that ingests and deletions
  /// revisit, kept between them: the next ingest's revisits mostly read the same sources
  /// (about 60 ms of decoding and detection for a 2048×1024 panorama, 30 ms of loading and gap
  /// fill for a million returns). 0 keeps none.
  int64_t max_revisit_image_bytes = 256ll << 20;
};

/// Summary of a project (catalog + HEAD version).
struct ProjectInfo {
  std::string name;
  std::string description;
  double vossel_size_m = 0.0;
  int64_t head_version = 0;
  int64_t scan_count = 0;
  int64_t vossel_count = 0;
  int64_t record_count = 0;
  std::string created_utc;
  /// The origin x_0 (VASL-MODEL §1): world = lattice + x_0; unset until given at creation or
  /// fixed by the first scan (its position rounded to the kilometre).
  std::optional<Eigen::Vector3d> origin_m;
  /// Set (ListProjects only) when the project cannot be opened: what is wrong with it. The
  /// other fields are then empty; the other projects are listed as usual.
  std::string problem;
};

using ingest::LidarData;
using ingest::PanoramaData;
using ingest::ScanInput;
using ingest::Progress;
using ingest::ProgressFn;
using render::RenderImage;
using render::RenderRequest;

struct IngestResult {
  int64_t scan_id = 0;
  int64_t version = 0;          ///< the committed version
  int64_t vossel_count = 0;     ///< vossels in the new version
  int64_t record_count = 0;     ///< records in the new version
  int64_t new_vossels = 0;      ///< vossels this change added (negative: removed)
  int64_t sources_computed = 0;   ///< sources computed on every tile (the new scan's; all in a rebuild)
  int64_t sources_revisited = 0;  ///< older sources recomputed on the tiles the change reaches
  int64_t pairs_revisited = 0;    ///< (older source, tile) pairs with records recomputed
  int64_t blocks_revisited = 0;   ///< (older source, 16³-vossel block) pairs recomputed
  int64_t vossels_revisited = 0;  ///< (older source, vossel) pairs of those blocks recomputed
  int64_t vossels_in_blocks = 0;  ///< (older source, vossel) pairs those blocks hold
  /// Of the sources revisited, those refreshed from their own records without their blob.
  int64_t sources_refreshed = 0;
  int64_t tiles_changed = 0;      ///< tiles whose objects the commit wrote
  int64_t bytes_written = 0;      ///< bytes the commit wrote
  /// Records the change computed, and the records of the tiles whose records it rewrote (the
  /// others of them carried over unchanged). An ingest's, a back-projection's, a deletion's.
  int64_t records_computed = 0;
  int64_t records_rewritten = 0;
  store::CommitTimes commit_times;  ///< where its commit's time went (a benchmark's figures)
  int64_t pixels_back_projected = 0;  ///< back-projection: pixels that became derived records
  int64_t pixels_outside = 0;         ///< back-projection: pixels whose point is in no vossel
  int64_t pixels_invalid = 0;         ///< back-projection: surface pixels with a non-finite colour
  /// Ingest: §2.3 calibration health of each camera of the scan (by name) against its LiDAR
  /// (ingest/calibration.h); none for a camera-only scan.
  std::vector<std::pair<std::string, records::CalibrationHealth>> calibration;
  double seconds = 0.0;         ///< wall time of the whole flow
  std::vector<std::pair<std::string, double>> stage_seconds;  ///< per stage, in order
  /// A retry: the change had already committed under its request id, and was not done again.
  /// Only `version`, `scan_id` and `answer` are then set.
  bool replayed = false;
  std::string answer;           ///< replayed: the answer recorded (SetOperationAnswer), may be empty
};

using flows::BackProjectInput;

/// What InspectRecords reports of a version's records.
struct RecordsInspection {
  int64_t version = 0;      ///< the version inspected (HEAD resolved)
  int64_t tile_count = 0;   ///< tiles in its manifest
  int64_t record_count = 0;
  std::vector<records::AttributeInfo> attributes;  ///< as stored in its tile files
};

class Engine {
 public:
  /// Opens (creating if needed) the data directory holding one folder per project.
  static absl::StatusOr<std::unique_ptr<Engine>> Open(const std::filesystem::path& data_dir,
                                                      const EngineLimits& limits = {});
  ~Engine();

  const EngineLimits& limits() const;

  /// Project names: 1-63 characters of [a-z0-9._-], starting with a letter or digit.
  absl::StatusOr<ProjectInfo> CreateProject(const std::string& name,
                                            const store::ProjectSettings& settings);
  absl::StatusOr<ProjectInfo> GetProject(const std::string& name);
  absl::StatusOr<std::vector<ProjectInfo>> ListProjects();
  absl::StatusOr<std::vector<store::ScanInfo>> ListScans(const std::string& project);
  /// A visual reference of a live scan (world pose) and its image bytes as sent. NOT_FOUND
  /// naming the scan, or the reference and the ones the scan has.
  absl::StatusOr<std::pair<store::VisualReferenceInfo, std::string>> GetVisualReference(
      const std::string& project, const std::string& scan, const std::string& name);
  /// The confidence maps of a scan's cameras (VASL-MODEL §9: what each artefact lowered and
  /// where), found again from the stored images as their ingest found them.
  absl::StatusOr<std::vector<flows::SourceConfidence>> ScanConfidence(const std::string& project,
                                                                      const std::string& scan);

  /// The ingest flow: validate (nothing is stored if this fails) → store blobs → voxelise →
  /// normals → visibility → records → fuse → atomic commit. `progress` may be empty.
  absl::StatusOr<IngestResult> IngestScan(const std::string& project, const ScanInput& scan,
                                          const ProgressFn& progress = {});

  /// Back-projection (§10): the image's pixels become derived records (modality derived,
  /// V = 1) of the vossels they land on, in a new batch that is a scan of its own (delete it to
  /// roll the batch back); raw records are never replaced. INVALID_ARGUMENT for an image
  /// without R, G, B, Z, a bad pose or projection, or no pixel landing on geometry; NOT_FOUND
  /// for an unknown render; ALREADY_EXISTS for a name in use.
  absl::StatusOr<IngestResult> BackProject(const std::string& project, BackProjectInput input,
                                           const ProgressFn& progress = {});

  /// Recomputes the whole project from its raw blobs as a new version (the oracle the
  /// incremental flows agree with). FAILED_PRECONDITION for a project without scans.
  absl::StatusOr<IngestResult> Rebuild(const std::string& project, const ProgressFn& progress = {},
                                       const std::string& request_id = "");

  /// A new version without scan `scan`: its records and geometry leave, the tiles it touched
  /// are recomputed from the other scans' blobs; its blobs go when retention drops the last
  /// version that has it. NOT_FOUND for an unknown scan.
  absl::StatusOr<IngestResult> DeleteScan(const std::string& project, const std::string& scan,
                                          const ProgressFn& progress = {},
                                          const std::string& request_id = "");

  /// Changes under a request id (ScanInput::request_id, BackProjectInput::request_id and the
  /// `request_id` of Rebuild and DeleteScan): one that committed is recorded with its version
  /// in the same transaction, and a retry under the same id gets IngestResult::replayed
  /// instead of a second change (FAILED_PRECONDITION when the id named another change;
  /// INVALID_ARGUMENT for a malformed id). FindOperation: the change committed under
  /// `asked.request_id`, or nullopt (with `asked.kind` set, FAILED_PRECONDITION when the id was
  /// used for another change); SetOperationAnswer keeps the caller's answer (any bytes) with it.
  absl::StatusOr<std::optional<store::OperationRecord>> FindOperation(
      const std::string& project, const store::OperationRecord& asked);
  absl::Status SetOperationAnswer(const std::string& project, const std::string& request_id,
                                  const std::string& answer);

  /// Versions still kept, oldest first, with what made each and the bytes it wrote.
  absl::StatusOr<std::vector<store::VersionInfo>> ListVersions(const std::string& project);

  /// Writes version `version` (0: HEAD) of a project as one merged OpenVDB file at `path`
  /// (flows::Export). FAILED_PRECONDITION for a project without versions.
  absl::StatusOr<flows::ExportResult> Export(const std::string& project, int64_t version,
                                             const std::filesystem::path& path);

  /// Weighting profiles (§7). CreateProfile stores a new revision of `profile.name` (1 for a
  /// new name); "default" is built in and cannot be redefined.
  absl::StatusOr<reweight::NamedProfile> CreateProfile(const std::string& project,
                                                       const fusion::WeightingProfile& profile);
  /// The built-in default and the latest revision of every stored profile; `active` is set to
  /// the project's active profile name.
  absl::StatusOr<std::vector<reweight::NamedProfile>> ListProfiles(const std::string& project,
                                                                   std::string* active);
  /// Profile `name` at `revision` (0: latest; empty name: the active profile).
  absl::StatusOr<reweight::NamedProfile> GetProfile(const std::string& project,
                                                    const std::string& name, int32_t revision);
  /// The profile renders, queries and ingest use when none is named.
  absl::Status SetActiveProfile(const std::string& project, const std::string& name);

  /// The reweight flow (§7): a new version whose tiles hold fused values under profile `name`
  /// at `revision` (0: latest; empty: active), from the stored records alone. Under a request
  /// id as the other changes (its subject "NAME@REVISION"); a reweight that changed nothing
  /// (ReweightResult::unchanged) commits nothing and records no id.
  absl::StatusOr<reweight::ReweightResult> Reweight(const std::string& project,
                                                    const std::string& name, int32_t revision,
                                                    const ProgressFn& progress = {},
                                                    const std::string& request_id = "");

  /// Multi-scan radiometric normalisation (§7) of HEAD's RGB records weighed under profile
  /// `base` (empty: active): the gains become a new revision of profile `name` (empty: base's
  /// name, "normalised" for the default). Reweight under it to store its fused tiles.
  absl::StatusOr<reweight::NormaliseOutcome> Normalise(const std::string& project,
                                                       const std::string& base,
                                                       const std::string& name);

  /// Lens dirt and fog (§9) of a rig's camera, found from its frames in HEAD's period
  /// (reweight::EstimateLensProfile) under profile `base` (empty: active): the map is kept in
  /// the catalog and a new revision of profile `request.name` applies it. Reweight under it to
  /// store its fused tiles.
  absl::StatusOr<reweight::LensOutcome> EstimateLens(const std::string& project,
                                                     const std::string& base,
                                                     const reweight::LensRequest& request);
  /// The project's lens maps, by id.
  absl::StatusOr<std::vector<fusion::LensMap>> ListLensMaps(const std::string& project);

  /// Provenance query on version `version` (0: HEAD): the records of the vossels whose cells
  /// meet the world box, with their weights under profile `profile` (empty: active).
  absl::StatusOr<flows::RecordsQueryResult> QueryRecords(const std::string& project,
                                                         int64_t version,
                                                         const Eigen::Vector3d& min_m,
                                                         const Eigen::Vector3d& max_m,
                                                         const std::string& profile,
                                                         int64_t limit);

  /// A new version that gives back kept version `version` (flows::Rollback): its tiles, its
  /// fused layers and its scans.
  absl::StatusOr<IngestResult> Rollback(const std::string& project, int64_t version,
                                        const ProgressFn& progress = {});

  /// Pins (or unpins) a kept version against retention.
  absl::Status SetPinned(const std::string& project, int64_t version, bool pinned);

  /// The render flow (§8) on an immutable snapshot, under the request's profile: its fused
  /// tiles when the version holds them on every tile, else fused for this render (the image
  /// says so).
  absl::StatusOr<RenderImage> Render(const std::string& project, const RenderRequest& request);

  /// Record attributes of a version (0: HEAD) with type, codec and stride, and its size.
  absl::StatusOr<RecordsInspection> InspectRecords(const std::string& project, int64_t version);

 private:
  struct Impl;
  explicit Engine(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace vasl

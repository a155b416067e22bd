/// @file project_store.h
/// @brief One project on disk: catalog.sqlite (WAL), content-addressed blobs, tiled versions
///        whose tile files are content-addressed objects, and an atomically replaced HEAD
///        (ARCHITECTURE.md, "Storage of one project").
/// @details Layout of `<data-dir>/<project>/`:
///            catalog.sqlite   settings, scans, sources, batches, versions and their manifests
///            blobs/<sha256>   raw inputs: packed LiDAR points, encoded images and masks
///            objects/<sha256> tile files (plain OpenVDB: geometry, records, fused-default per
///                             tile) and reach rasters, through the ObjectStore interface
///            HEAD             the committed version number, replaced by atomic rename
///          A version is a manifest: for each tile and layer the hash of its object, and for
///          each source the hash of its reach raster. A commit writes only the objects of the
///          tiles it changed (put without waiting on the disk, then fsynced together and named
///          by ObjectStore::Sync), then the catalog rows of the new manifest in one
///          transaction, then renames HEAD. A crash at any point leaves the previous version
///          intact: catalog rows newer than HEAD are dropped on Open, and objects no kept
///          version references are collected.
/// @warning One writer per project at a time (the caller serialises commits); readers may load
///          snapshots concurrently with a writer.
#pragma once

#include <cstdint>
#include <filesystem>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <set>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "lattice/geometry/pose.h"
#include "lattice/records/calibration.h"
#include "lattice/records/records.h"
#include "lattice/store/object_store.h"
#include "lattice/tiles/tiling.h"

namespace vasl::store {

/// OK for a valid project name: 1-63 characters of [a-z0-9._-], starting with a letter or
/// digit (so never "." or ".."); INVALID_ARGUMENT saying so otherwise.
absl::Status ValidateProjectName(const std::string& name);

/// OK for a valid request id (OperationRecord): 1-128 characters of [A-Za-z0-9._:-] (a UUID
/// fits); INVALID_ARGUMENT saying so otherwise.
absl::Status ValidateRequestId(const std::string& id);

/// Settings fixed when a project is created.
struct ProjectSettings {
  double vossel_size_m = 0.02;  ///< vossel edge h, metres (§1)
  std::string description;      ///< free text
  int keep_versions = 5;        ///< retention: versions kept besides HEAD's (and pinned ones)
  int tile_vossels = tiles::kDefaultTileVossels;  ///< tile edge T in vossels (power of 2, 8-512)
  /// The origin x_0 given at creation (VASL-MODEL §1), world metres; unset: the first scan's
  /// commit fixes it (ProposeOrigin). ProjectStore::origin() is the current one.
  std::optional<Eigen::Vector3d> origin_m;
};

/// One observation source: the LiDAR of a scan, or one of its cameras. Its id is the `scan`
/// field of every record it produced (§6).
struct SourceInfo {
  int32_t id = 0;                   ///< record `scan` field; unique in the project
  int64_t scan_id = 0;              ///< the scan (ingest unit) it belongs to
  std::string name;                 ///< "lidar" or the panorama's name
  records::Modality modality = records::Modality::kUnspecified;
  geometry::Pose pose;              ///< T_world_sensor of this source
  std::string blob_sha256;          ///< LiDAR: packed float32 (x,y,z,intensity); camera: image bytes
  int width_px = 0;                 ///< camera image size; 0 for LiDAR
  int height_px = 0;
  double divergence_rad = 0.0;      ///< LiDAR beam divergence, or camera angular resolution (0: from image size)
  int64_t point_count = 0;          ///< LiDAR points; 0 for cameras
  /// Derived sources (§10): the image's projection, "equirect" or "pinhole fx fy cx cy k1 k2 k3
  /// p1 p2" and, after "render", the render it came from. Empty for LiDAR and cameras.
  std::string camera;
  /// A camera sent with a mask image (ingest::PanoramaData::encoded_mask): its blob; empty:
  /// none.
  std::string mask_sha256;
  /// A camera of a scan with LiDAR: its §2.3 calibration health against that LiDAR, found at
  /// ingest. Unset for LiDAR, derived sources and cameras of camera-only scans.
  std::optional<records::CalibrationHealth> calibration;
};

/// A photo kept with a scan for people to look at (an E57 visual reference): no projection,
/// no source, no records; its blob lives as long as a kept version has the scan.
struct VisualReferenceInfo {
  std::string name;                 ///< unique within the scan, among its images
  geometry::Pose pose;              ///< the pose it was sent with
  std::string blob_sha256;          ///< the image bytes as sent
  int width_px = 0;
  int height_px = 0;
  int64_t size_bytes = 0;
};

/// One ingested scan with its sources.
struct ScanInfo {
  int64_t id = 0;                   ///< catalog id, assigned by CommitScan
  std::string name;                 ///< client's scan id, unique in the project
  std::string rig;                  ///< rig / device name
  std::string captured_utc;         ///< capture time as given by the client (ISO 8601), may be empty
  geometry::Pose pose;              ///< the scan's (LiDAR's) pose
  int32_t batch = 0;                ///< batch id of its records
  int64_t version = 0;              ///< version that committed it
  int64_t deleted_in = 0;           ///< version that deleted it; 0: not deleted
  std::string created_utc;          ///< server time of ingest, ISO 8601
  std::vector<SourceInfo> sources;
  std::vector<VisualReferenceInfo> visual_references;
};

/// One object of a version's manifest.
struct ManifestEntry {
  std::string object;    ///< sha256 of the object (objects/<sha256>)
  int64_t vossels = 0;   ///< vossels of the tile
  int64_t records = 0;   ///< records of the tile (records layer)
  int64_t bytes = 0;     ///< size of the object
};

/// Layers of a tile: its geometry, its records and its fused values under a profile.
inline constexpr char kLayerGeometry[] = "geometry";
inline constexpr char kLayerRecords[] = "records";
inline constexpr char kLayerFusedDefault[] = "fused-default";
/// The layer of fused values under profile `name` at `revision`: "fused-default" for the
/// built-in default profile, "fused-<name>@<revision>" for the others.
std::string FusedLayerName(const std::string& name, int32_t revision);
/// The profile name and revision of a fused layer other than the default's; false otherwise.
bool ParseFusedLayerName(const std::string& layer, std::string* name, int32_t* revision);

/// A version's manifest: per tile and layer its object; per source its reach raster.
struct Manifest {
  std::map<tiles::TileKey, std::map<std::string, ManifestEntry>> tiles;
  std::map<int32_t, ManifestEntry> reach;  ///< source id → its reach raster's object
};

/// The fused layers besides the default's that every tile of `manifest` holds.
std::vector<std::string> CompleteProfileLayers(const Manifest& manifest);

/// An immutable version of a project, loaded whole into memory.
struct Snapshot {
  int64_t version = 0;  ///< 0: the empty project
  int tile_vossels = tiles::kDefaultTileVossels;
  records::VosselGeometry geometry;  ///< every vossel, canonical order, with sums
  records::RecordSet records;        ///< sorted by vossel
  records::FusedValues fused;        ///< under the default profile
  /// Fused values under other profiles, by layer (FusedLayerName): a commit writes each of
  /// them for the tiles it changes; LoadSnapshot fills the layers asked for.
  std::map<std::string, records::FusedValues> profile_fused;
  Manifest manifest;
  std::map<int32_t, tiles::ReachRaster> reach;  ///< source id → its reach raster
  /// Loaded with only some tiles (LoadSnapshot's `only_tiles`): geometry, records and fused
  /// values are those tiles', `reach` is empty. No flow that changes a project takes one.
  bool partial = false;
  /// The records were read (LoadSnapshot's `with_records`), or hold only some tiles': an
  /// ingest within a memory budget reads the records of the tiles it touches (LoadRecords) and
  /// its new snapshot holds those tiles' records alone; Commit then counts from the manifest.
  bool records_loaded = true;
  bool records_partial = false;
};

/// Summary of a committed version, kept in the catalog.
struct VersionInfo {
  int64_t version = 0;
  int64_t vossel_count = 0;
  int64_t record_count = 0;
  int64_t tile_count = 0;
  int64_t bytes_written = 0;  ///< bytes of the objects this version's commit wrote
  int64_t bytes_total = 0;    ///< bytes of every object its manifest references
  std::string made_by;        ///< "ingest scan S", "rebuild", "delete scan S", ...
  bool pinned = false;
  std::string created_utc;
};

/// A change a client asked for under its own request id: recorded with the version it
/// committed, in that version's transaction, so that a retry of a call whose answer was lost
/// (deadline, dropped connection, restart) finds the version instead of doing the work again.
struct OperationRecord {
  std::string request_id;
  std::string kind;      ///< "ingest", "back-project", "rebuild", "delete"
  std::string subject;   ///< the scan or batch it names ("" for a rebuild)
  int64_t version = 0;   ///< the version it committed
  int64_t scan_id = 0;   ///< the scan it added (ingest, back-projection), else 0
  std::string answer;    ///< the caller's answer, opaque to the store (SetOperationAnswer)
  std::string created_utc;
};

/// What a commit changes (the single writer builds it next to the new snapshot).
struct CommitPlan {
  std::string made_by;
  /// Tiles whose geometry changed: all their layers are rewritten (a tile left without vossels
  /// leaves the manifest).
  std::set<tiles::TileKey> geometry_tiles;
  /// Tiles whose records (and so fused values) changed; their geometry object is kept.
  std::set<tiles::TileKey> record_tiles;
  /// Sources whose reach raster changed (taken from the snapshot).
  std::set<int32_t> reach_sources;
  /// Sources whose reach raster leaves the manifest (a deleted scan's).
  std::set<int32_t> drop_reach;
  /// Every tile and reach raster of the snapshot is written; the previous manifest is dropped.
  bool replace_all = false;
  /// With replace_all: the new version's tiles, every layer put beforehand (ProjectStore::
  /// PutTiles; a rebuild in tile groups). The snapshot's geometry and records are then not
  /// written (it may hold no records); its reach rasters are.
  std::map<tiles::TileKey, std::map<std::string, ManifestEntry>> put_tiles;
  /// A scan to add (its sources must carry ids from NextSourceId).
  std::optional<ScanInfo> add_scan;
  /// Tiles each added LiDAR source has returns in.
  std::map<int32_t, std::set<tiles::TileKey>> source_tiles;
  /// Name of a scan this version deletes.
  std::string delete_scan;
  /// Objects already put in the object store (a reweight's fused tiles), set as the given
  /// layers of tiles the previous version has.
  std::map<tiles::TileKey, std::map<std::string, ManifestEntry>> put_layers;
  /// The commit changes layers only (put_layers): the snapshot is not read, the new version
  /// keeps the previous one's geometry, records and counts.
  bool layers_only = false;
  /// > 0: a rollback. The new version's manifest, counts and live scans are those of this
  /// kept version (scans added since end, scans deleted since live again); nothing else may be
  /// set and the snapshot is not read.
  int64_t rollback_to = 0;
};

/// A render as the catalog records it, so that an image that comes back can cite it.
struct RenderRecord {
  int64_t id = 0;            ///< assigned by RecordRender
  int64_t version = 0;
  std::string profile;
  int32_t revision = 0;
  std::string projection;    ///< "equirect" or "pinhole"
  int width_px = 0, height_px = 0;
  geometry::Pose pose;       ///< T_world_camera
  std::string camera;        ///< projection parameters as text (pinhole intrinsics), may be empty
  std::string created_utc;
};

/// A weighting profile revision as the catalog keeps it; its text is fusion::ProfileToText's.
struct StoredProfile {
  std::string name;
  int32_t revision = 0;
  std::string text;
  std::string created_utc;
};

/// A lens dirt and fog map (VASL-MODEL §9) as the catalog keeps it; its text is
/// fusion::LensMapToText's.
struct StoredLensMap {
  int64_t id = 0;
  std::string rig;
  std::string camera;
  std::string text;
  std::string created_utc;
};

/// Where a commit's time went (ProjectStore::LastCommitTimes): the seconds of thread time its
/// tiles' steps took, summed over the threads that wrote them, and the wall seconds of each of
/// its steps. For benchmarks and diagnostics; nothing reads it to decide.
struct CommitTimes {
  // Thread seconds, over every tile written.
  double cut_s = 0.0;       ///< cutting the tiles' vossels, records and fused values out
  double geometry_s = 0.0;  ///< encoding geometry objects
  double records_s = 0.0;   ///< encoding records objects
  double fused_s = 0.0;     ///< encoding fused objects (every layer)
  double put_s = 0.0;       ///< hashing and writing the objects (ObjectStore::PutBytes)
  // Wall seconds, in commit order.
  double tiles_wall_s = 0.0;    ///< writing the tiles' objects (the steps above, in parallel)
  double reach_wall_s = 0.0;    ///< writing the reach rasters
  double sync_wall_s = 0.0;     ///< waiting for every object to be on the disk
  double catalog_wall_s = 0.0;  ///< the catalog's transaction
  double head_wall_s = 0.0;     ///< replacing HEAD
  double collect_wall_s = 0.0;  ///< retention's collection after it
};

class ProjectStore {
 public:
  /// Creates `dir` (must not exist) with an empty catalog and HEAD = 0.
  static absl::StatusOr<std::unique_ptr<ProjectStore>> Create(const std::filesystem::path& dir,
                                                              const std::string& name,
                                                              const ProjectSettings& settings);
  /// Opens an existing project directory; NOT_FOUND if it is not one.
  static absl::StatusOr<std::unique_ptr<ProjectStore>> Open(const std::filesystem::path& dir);
  ~ProjectStore();

  const std::string& name() const;
  const ProjectSettings& settings() const;
  const std::string& created_utc() const;
  const std::filesystem::path& dir() const;
  /// The committed version; 0 for a project with no scan yet.
  int64_t head_version() const;
  /// The project's origin x_0 (VASL-MODEL §1): world = lattice + x_0. Unset until given at
  /// creation or fixed by the first commit that adds a scan; never changes once fixed.
  std::optional<Eigen::Vector3d> origin() const;
  /// Catalog summary of the HEAD version (zeros for version 0).
  absl::StatusOr<VersionInfo> HeadInfo() const;
  /// The times of the last commit that succeeded (zeros before one).
  CommitTimes LastCommitTimes() const;

  /// Stores bytes content-addressed; returns the lowercase sha256 hex. Idempotent, fsynced.
  absl::StatusOr<std::string> PutBlob(std::string_view bytes);
  absl::StatusOr<std::string> ReadBlob(const std::string& sha256) const;

  /// Scans in ingest order, with their sources.
  /// (`version`: the scans of that version; 0: HEAD's. Deleted scans are not listed.)
  absl::StatusOr<std::vector<ScanInfo>> ListScans(int64_t version = 0) const;
  /// True if a scan with this client name exists.
  absl::StatusOr<bool> HasScan(const std::string& name) const;
  /// Next unused source id / batch id (valid until the next commit; single writer).
  absl::StatusOr<int32_t> NextSourceId() const;
  absl::StatusOr<int32_t> NextBatchId() const;

  /// Tiles in which a LiDAR source has returns (recorded when its scan was committed).
  absl::StatusOr<std::set<tiles::TileKey>> SourceTiles(int32_t source_id) const;

  /// Loads version `version` (0: an empty snapshot with this project's vossel size), with the
  /// fused layers `profile_layers` (FusedLayerName) besides the default's. Without
  /// `with_records` the snapshot's records stay empty and no record object is read (a caller
  /// after one fused layer).
  /// With `only_tiles` the snapshot is partial: it holds those tiles of the version alone (the
  /// others are not read; its manifest is still the whole version's) and no reach raster, so
  /// that a reader bounds what it holds (flows/tile_budget.h).
  /// NOT_FOUND when it does not exist or retention removed it, or a layer is missing from a tile.
  absl::StatusOr<std::shared_ptr<const Snapshot>> LoadSnapshot(
      int64_t version, const std::vector<std::string>& profile_layers = {},
      bool with_records = true, const std::set<tiles::TileKey>* only_tiles = nullptr) const;
  /// The manifest of a kept version.
  absl::StatusOr<Manifest> LoadManifest(int64_t version) const;
  /// The records of version `version`'s tiles `tiles` (those it has), numbered by `geometry`,
  /// the version's whole geometry (a snapshot of it loaded without records), sorted by vossel.
  absl::StatusOr<records::RecordSet> LoadRecords(int64_t version,
                                                 const std::set<tiles::TileKey>& tiles,
                                                 const records::VosselGeometry& geometry) const;
  /// The tiles of version `version` holding a record of any of `sources`: every tile's records
  /// are read, one tile per thread at a time (a deletion within a memory budget).
  absl::StatusOr<std::set<tiles::TileKey>> TilesWithRecordsOf(
      int64_t version, const std::set<int32_t>& sources) const;

  /// Atomic commit of a new version: `snapshot` holds the whole new state, `plan` says what
  /// changed. Writes the changed tiles' objects, the manifest rows, the scan rows, then HEAD;
  /// runs retention. Returns the new version number.
  absl::StatusOr<int64_t> Commit(const Snapshot& snapshot, const CommitPlan& plan);
  /// Writes every layer of the tiles `tiles` of `snapshot` (which need hold the records of
  /// those tiles alone, sorted by vossel) as objects, before a commit names them: a rebuild in
  /// tile groups puts each group so, then commits them all (CommitPlan::put_tiles). Call under
  /// the project's one writer, before its Commit: until a commit names them they are garbage
  /// that the next collection removes. Tiles without vossels are left out.
  absl::StatusOr<std::map<tiles::TileKey, std::map<std::string, ManifestEntry>>> PutTiles(
      const Snapshot& snapshot, const std::set<tiles::TileKey>& tiles);

  /// Stores a new revision of profile `name` (1 + the latest; 1 for a new name) made by
  /// `text_of(revision)`, and returns it. Profiles are project metadata, not versioned data.
  absl::StatusOr<StoredProfile> PutProfile(
      const std::string& name, const std::function<std::string(int32_t revision)>& text_of);
  /// Revision `revision` of profile `name` (0: the latest). NOT_FOUND when there is none.
  absl::StatusOr<StoredProfile> GetProfile(const std::string& name, int32_t revision = 0) const;
  /// The latest revision of every stored profile, by name.
  absl::StatusOr<std::vector<StoredProfile>> ListProfiles() const;
  /// Stores a lens map of `rig`'s `camera` and returns it with its id (1 + the largest).
  /// Lens maps are project metadata, as profiles: no version holds them.
  absl::StatusOr<StoredLensMap> PutLensMap(const std::string& rig, const std::string& camera,
                                           const std::string& text);
  /// Lens map `id`; NOT_FOUND when there is none.
  absl::StatusOr<StoredLensMap> GetLensMap(int64_t id) const;
  /// Every lens map, by id.
  absl::StatusOr<std::vector<StoredLensMap>> ListLensMaps() const;
  /// The profile renders, queries and ingest fusion use when none is named ("default" until set).
  absl::StatusOr<std::string> ActiveProfile() const;
  absl::Status SetActiveProfile(const std::string& name);

  /// Records a render and returns its id (ids grow; they are never reused).
  absl::StatusOr<int64_t> RecordRender(const RenderRecord& render);
  /// A recorded render; NOT_FOUND for an unknown id.
  absl::StatusOr<RenderRecord> GetRender(int64_t id) const;

  /// Versions still kept (not removed by retention), oldest first.
  absl::StatusOr<std::vector<VersionInfo>> ListVersions() const;
  /// Pins (or unpins) a version: a pinned version survives retention. NOT_FOUND if not kept.
  absl::Status SetPinned(int64_t version, bool pinned);
  /// Retention: versions older than the newest keep_versions + 1 and not pinned are dropped,
  /// then every object and blob that no kept version references is removed. Returns the number
  /// of files removed. Commit and Open run it.
  /// @warning Call it only from the project's single writer, between its commits: the blobs of
  /// a scan stored but not yet committed are not referenced by any version and would go.
  absl::StatusOr<int64_t> CollectGarbage();

  /// The object store holding tile files and reach rasters.
  const ObjectStore& objects() const;
  /// The same, for the single writer that puts objects before a commit names them
  /// (CommitPlan::put_layers). Objects no version names are collected by the next commit.
  ObjectStore& writable_objects();
  /// Lists the record attributes of a version's records (type, codec, stride) from one of its
  /// tile files.
  absl::StatusOr<std::vector<records::AttributeInfo>> InspectRecords(int64_t version) const;

  /// Points of Commit after which a test can inject a failure.
  /// The change the writer runs now under a client's request id: the next Commit records it
  /// (OperationRecord) with its version. Call with the writer lock held; EndOperation after the
  /// flow, whatever its outcome (OperationScope does both).
  void BeginOperation(const OperationRecord& op);
  /// Forgets BeginOperation's record and ProposeOrigin's origin.
  void EndOperation();
  /// The change the writer runs now fixes the origin: the next Commit records `origin_m` in its
  /// transaction when the project has none yet (so a change that fails fixes nothing). Call
  /// with the writer lock held, inside an OperationScope.
  void ProposeOrigin(const Eigen::Vector3d& origin_m);
  /// The committed change recorded under `request_id`, or nullopt.
  absl::StatusOr<std::optional<OperationRecord>> FindOperation(const std::string& request_id) const;
  /// Keeps the caller's answer (any bytes) with a committed operation.
  absl::Status SetOperationAnswer(const std::string& request_id, const std::string& answer);

  enum class CommitStage {
    kNone,          ///< no injected failure
    kAfterObjects,  ///< tile objects written and fsynced
    kAfterCatalog,  ///< catalog rows committed, HEAD not yet replaced
  };
  /// Test hook: the next Commit fails with INTERNAL right after `stage`. With `simulate_crash`
  /// it returns without any cleanup, leaving the disk as a crash at that point would (a later
  /// Open must recover); otherwise it cleans up as for a real IO failure.
  void InjectCommitFailureForTesting(CommitStage stage, bool simulate_crash);

 private:
  struct Impl;
  explicit ProjectStore(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

/// BeginOperation for the life of the scope (nothing with an empty request id).
class OperationScope {
 public:
  OperationScope(ProjectStore& store, const OperationRecord& op) : store_(store) {
    if (!op.request_id.empty()) store_.BeginOperation(op);
  }
  ~OperationScope() { store_.EndOperation(); }
  OperationScope(const OperationScope&) = delete;
  OperationScope& operator=(const OperationScope&) = delete;

 private:
  ProjectStore& store_;
};

}  // namespace vasl::store

/// @file project_store.h
/// @brief One project on disk: catalog.sqlite (WAL), content-addressed blobs, immutable
///        versions and an atomically replaced HEAD (ARCHITECTURE.md, "Storage of one project").
/// @details Layout of `<data-dir>/<project>/`:
///            catalog.sqlite   settings, scans, sources, batches, versions (WAL mode)
///            blobs/<sha256>   raw inputs: packed LiDAR points, encoded images
///            versions/<n>/    records.vdb, geometry.vdb, fused-<profile>.vdb
///            HEAD             the committed version number, replaced by atomic rename
///          A commit writes versions/<n+1>/ beside the old one, fsyncs, commits the catalog
///          rows, then renames HEAD. A crash at any point leaves the previous version intact;
///          catalog rows of a version newer than HEAD are dropped on Open.
/// @warning One writer per project at a time (the caller serialises commits); readers may load
///          snapshots concurrently with a writer.
#pragma once

#include <cstdint>
#include <filesystem>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "lattice/geometry/pose.h"
#include "lattice/records/records.h"

namespace vasl::store {

/// Settings fixed when a project is created.
struct ProjectSettings {
  double vossel_size_m = 0.02;  ///< vossel edge h, metres (§1)
  std::string description;      ///< free text
  int keep_versions = 5;        ///< retention: versions kept besides HEAD's
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
  std::string created_utc;          ///< server time of ingest, ISO 8601
  std::vector<SourceInfo> sources;
};

/// An immutable version of a project.
struct Snapshot {
  int64_t version = 0;  ///< 0: the empty project
  records::VosselGeometry geometry;
  records::RecordSet records;
  records::FusedValues fused;  ///< under the default profile
};

/// Summary of a committed version, kept in the catalog.
struct VersionInfo {
  int64_t version = 0;
  int64_t vossel_count = 0;
  int64_t record_count = 0;
  std::string created_utc;
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
  /// Catalog summary of the HEAD version (zeros for version 0).
  absl::StatusOr<VersionInfo> HeadInfo() const;

  /// Stores bytes content-addressed; returns the lowercase sha256 hex. Idempotent, fsynced.
  absl::StatusOr<std::string> PutBlob(std::string_view bytes);
  absl::StatusOr<std::string> ReadBlob(const std::string& sha256) const;

  /// Scans in ingest order, with their sources.
  absl::StatusOr<std::vector<ScanInfo>> ListScans() const;
  /// True if a scan with this client name exists.
  absl::StatusOr<bool> HasScan(const std::string& name) const;
  /// Next unused source id / batch id (valid until the next commit; single writer).
  absl::StatusOr<int32_t> NextSourceId() const;
  absl::StatusOr<int32_t> NextBatchId() const;

  /// Loads version `version` (0: an empty snapshot with this project's vossel size).
  absl::StatusOr<std::shared_ptr<const Snapshot>> LoadSnapshot(int64_t version) const;

  /// Atomic commit of a new version holding `snapshot` and the catalog rows of `scan`
  /// (its sources must carry the ids the records use). Returns the new version number.
  absl::StatusOr<int64_t> CommitScan(const Snapshot& snapshot, const ScanInfo& scan);

  /// Directory of a committed version; NOT_FOUND if it does not exist.
  absl::StatusOr<std::filesystem::path> VersionDir(int64_t version) const;
  /// Lists the record attributes of a version's records.vdb (type, codec, stride).
  absl::StatusOr<std::vector<records::AttributeInfo>> InspectRecords(int64_t version) const;

  /// Points of CommitScan after which a test can inject a failure.
  enum class CommitStage {
    kNone,                ///< no injected failure
    kAfterFiles,          ///< version files written and fsynced in the temp dir
    kAfterVersionRename,  ///< temp dir renamed to versions/<n>
    kAfterCatalog,        ///< catalog rows committed, HEAD not yet replaced
  };
  /// Test hook: the next CommitScan fails with INTERNAL right after `stage`. With
  /// `simulate_crash` it returns without any cleanup, leaving the disk as a crash at that point
  /// would (a later Open must recover); otherwise it cleans up as for a real IO failure.
  void InjectCommitFailureForTesting(CommitStage stage, bool simulate_crash);

 private:
  struct Impl;
  explicit ProjectStore(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace vasl::store

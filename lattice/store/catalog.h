/// @file catalog.h
/// @brief catalog.sqlite of one project: a thin RAII wrapper over SQLite (connection and
///        prepared statements) and the schema (ARCHITECTURE.md "Storage of one project").
/// @details Tables: schema_version, project (one row: settings), versions (with what made each),
///          manifest (per version, tile and layer: the content hash of its object), reach (per
///          version and source: the object of its reach raster), source_tiles (the tiles a
///          LiDAR source has returns in), scans (with the version that deleted them, if any),
///          sources, batches. Every row that belongs to a version carries its `version`, so that rows
///          newer than HEAD can be dropped on Open (crash recovery). Errors carry
///          sqlite3_errmsg and the database path.
/// @warning A Db is not synchronised by itself; ProjectStore guards it with a mutex.
#pragma once

#include <cstdint>
#include <filesystem>
#include <string>
#include <string_view>

#include "absl/status/statusor.h"

struct sqlite3;
struct sqlite3_stmt;

namespace vasl::store::internal {

/// 2: tiled versions (manifest, reach, source_tiles), scan deletion, made_by and pins.
inline constexpr int kCatalogSchemaVersion = 11;

/// One prepared statement; Bind* take 1-based parameter indices, Column* 0-based columns.
class Stmt {
 public:
  Stmt(sqlite3* db, sqlite3_stmt* stmt) : db_(db), stmt_(stmt) {}
  Stmt(Stmt&& other) noexcept;
  Stmt(const Stmt&) = delete;
  Stmt& operator=(const Stmt&) = delete;
  ~Stmt();

  Stmt& Bind(int i, int64_t v);
  Stmt& Bind(int i, double v);
  Stmt& Bind(int i, std::string_view v);
  /// Steps once: true if a row is available, false when done.
  absl::StatusOr<bool> Step();
  /// Steps until done (for statements without result rows).
  absl::Status Run();

  /// True when column `col` of the current row is NULL (e.g. of a LEFT JOIN that found none).
  bool IsNull(int col) const;
  int64_t Int(int col) const;
  double Real(int col) const;
  std::string Text(int col) const;

 private:
  sqlite3* db_;
  sqlite3_stmt* stmt_;
};

/// A connection to catalog.sqlite.
class Db {
 public:
  /// Opens (creating if `create`) the database in WAL mode with a 5 s busy timeout.
  static absl::StatusOr<Db> Open(const std::filesystem::path& path, bool create);
  Db(Db&& other) noexcept;
  Db(const Db&) = delete;
  Db& operator=(const Db&) = delete;
  ~Db();

  /// Runs one or more SQL statements without results.
  absl::Status Exec(std::string_view sql);
  absl::StatusOr<Stmt> Prepare(std::string_view sql);
  /// The rowid of the last row an INSERT on this connection added (sqlite3_last_insert_rowid).
  int64_t LastInsertRowId() const;
  /// The INTERNAL error for the last failure, "<what>: <path>: <sqlite3_errmsg>".
  absl::Status Error(std::string_view what) const;
  const std::filesystem::path& path() const { return path_; }

 private:
  Db(sqlite3* db, std::filesystem::path path) : db_(db), path_(std::move(path)) {}
  sqlite3* db_;
  std::filesystem::path path_;
};

/// Creates every table of schema version kCatalogSchemaVersion.
absl::Status CreateSchema(Db& db);
/// Brings a catalog of schema `from` (2 or later) to kCatalogSchemaVersion in one transaction:
/// 2 → 3 adds weighting profiles and the project's active profile; 3 → 4 keeps each scan's
/// spans of versions in scan_lives (a rollback can bring a deleted scan back); 4 → 5 records
/// every render (renders), so that what comes back can cite it; 5 → 6 keeps a source's
/// projection (sources.camera) for images sent back as derived data; 6 → 7 records the changes
/// clients asked for under a request id (operations), so that a retry finds its answer; 7 → 8
/// keeps the project's origin (VASL-MODEL §1), fixed at 0 for a project that has scans; 8 → 9
/// keeps cameras' calibration health and scans' visual references; 9 → 10 keeps lens dirt and
/// fog maps (§9).
absl::Status MigrateSchema(Db& db, int64_t from);

/// Deletes catalog rows of versions newer than `head` (versions, manifests, reach, source tiles,
/// scans, sources, batches, operations) and undoes deletions made by them, in one transaction.
absl::Status DropRowsNewerThan(Db& db, int64_t head);

}  // namespace vasl::store::internal

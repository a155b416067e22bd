#include "lattice/store/catalog.h"

#include <sqlite3.h>

#include "absl/strings/str_cat.h"

namespace vasl::store::internal {

Stmt::Stmt(Stmt&& other) noexcept : db_(other.db_), stmt_(other.stmt_) { other.stmt_ = nullptr; }
Stmt::~Stmt() {
  if (stmt_) sqlite3_finalize(stmt_);
}
Stmt& Stmt::Bind(int i, int64_t v) {
  sqlite3_bind_int64(stmt_, i, v);
  return *this;
}
Stmt& Stmt::Bind(int i, double v) {
  sqlite3_bind_double(stmt_, i, v);
  return *this;
}
Stmt& Stmt::Bind(int i, std::string_view v) {
  sqlite3_bind_text(stmt_, i, v.data(), static_cast<int>(v.size()), SQLITE_TRANSIENT);
  return *this;
}
absl::StatusOr<bool> Stmt::Step() {
  const int rc = sqlite3_step(stmt_);
  if (rc == SQLITE_ROW) return true;
  if (rc == SQLITE_DONE) return false;
  const std::string sql = sqlite3_sql(stmt_) ? sqlite3_sql(stmt_) : "";
  if ((rc & 0xff) == SQLITE_CONSTRAINT) {
    return absl::AlreadyExistsError(
        absl::StrCat("catalog constraint violated: ", sqlite3_errmsg(db_)));
  }
  return absl::InternalError(absl::StrCat("catalog statement failed (", sql.substr(0, 60),
                                          "...): ", sqlite3_errmsg(db_)));
}
absl::Status Stmt::Run() {
  for (;;) {
    absl::StatusOr<bool> row = Step();
    if (!row.ok()) return row.status();
    if (!*row) return absl::OkStatus();
  }
}
bool Stmt::IsNull(int col) const { return sqlite3_column_type(stmt_, col) == SQLITE_NULL; }

int64_t Stmt::Int(int col) const { return sqlite3_column_int64(stmt_, col); }
double Stmt::Real(int col) const { return sqlite3_column_double(stmt_, col); }
std::string Stmt::Text(int col) const {
  const unsigned char* t = sqlite3_column_text(stmt_, col);
  return t ? std::string(reinterpret_cast<const char*>(t),
                         static_cast<size_t>(sqlite3_column_bytes(stmt_, col)))
           : std::string();
}

absl::StatusOr<Db> Db::Open(const std::filesystem::path& path, bool create) {
  sqlite3* raw = nullptr;
  const int flags = SQLITE_OPEN_READWRITE | SQLITE_OPEN_FULLMUTEX | (create ? SQLITE_OPEN_CREATE : 0);
  const int rc = sqlite3_open_v2(path.c_str(), &raw, flags, nullptr);
  Db db(raw, path);
  if (rc != SQLITE_OK) {
    return absl::InternalError(absl::StrCat("cannot open catalog ", path.string(), ": ",
                                            raw ? sqlite3_errmsg(raw) : sqlite3_errstr(rc)));
  }
  sqlite3_busy_timeout(raw, 5000);
  // WAL: readers run concurrently with the writer; FULL sync makes commits durable.
  if (absl::Status s = db.Exec("PRAGMA journal_mode=WAL; PRAGMA synchronous=FULL; "
                               "PRAGMA foreign_keys=ON;");
      !s.ok()) {
    return s;
  }
  return db;
}

Db::Db(Db&& other) noexcept : db_(other.db_), path_(std::move(other.path_)) {
  other.db_ = nullptr;
}
Db::~Db() {
  if (db_) sqlite3_close_v2(db_);
}

int64_t Db::LastInsertRowId() const { return sqlite3_last_insert_rowid(db_); }

absl::Status Db::Exec(std::string_view sql) {
  char* err = nullptr;
  const std::string text(sql);
  if (sqlite3_exec(db_, text.c_str(), nullptr, nullptr, &err) != SQLITE_OK) {
    absl::Status s = absl::InternalError(
        absl::StrCat("catalog ", path_.string(), ": ", err ? err : sqlite3_errmsg(db_)));
    sqlite3_free(err);
    return s;
  }
  return absl::OkStatus();
}

absl::StatusOr<Stmt> Db::Prepare(std::string_view sql) {
  sqlite3_stmt* stmt = nullptr;
  if (sqlite3_prepare_v2(db_, sql.data(), static_cast<int>(sql.size()), &stmt, nullptr) !=
      SQLITE_OK) {
    return Error(absl::StrCat("cannot prepare \"", std::string(sql.substr(0, 60)), "\""));
  }
  return Stmt(db_, stmt);
}

absl::Status Db::Error(std::string_view what) const {
  return absl::InternalError(
      absl::StrCat(std::string(what), ": catalog ", path_.string(), ": ", sqlite3_errmsg(db_)));
}

namespace {

// Tables that later schemas added: one definition for a new catalog and for the migration.
constexpr char kScanLivesTable[] = R"sql(CREATE TABLE scan_lives(
  scan_id INTEGER NOT NULL REFERENCES scans(id) ON DELETE CASCADE,
  from_version INTEGER NOT NULL,
  to_version INTEGER,
  PRIMARY KEY (scan_id, from_version));
)sql";
constexpr char kProfilesTable[] = R"sql(CREATE TABLE profiles(
  name TEXT NOT NULL,
  revision INTEGER NOT NULL,
  body TEXT NOT NULL,
  created_utc TEXT NOT NULL,
  PRIMARY KEY (name, revision));
)sql";
constexpr char kRendersTable[] = R"sql(CREATE TABLE renders(
  id INTEGER PRIMARY KEY,
  version INTEGER NOT NULL,
  profile TEXT NOT NULL,
  revision INTEGER NOT NULL,
  projection TEXT NOT NULL,
  width_px INTEGER NOT NULL,
  height_px INTEGER NOT NULL,
  qx REAL NOT NULL, qy REAL NOT NULL, qz REAL NOT NULL, qw REAL NOT NULL,
  ox_m REAL NOT NULL, oy_m REAL NOT NULL, oz_m REAL NOT NULL,
  camera TEXT NOT NULL,
  created_utc TEXT NOT NULL);
)sql";

// A change a client asked for under its request id, with the version it committed (written in
// that version's transaction) and the answer the caller recorded afterwards (hex, may be empty).
constexpr char kOperationsTable[] = R"sql(CREATE TABLE operations(
  request_id TEXT PRIMARY KEY,
  kind TEXT NOT NULL,
  subject TEXT NOT NULL,
  version INTEGER NOT NULL,
  scan_id INTEGER NOT NULL DEFAULT 0,
  answer_hex TEXT NOT NULL DEFAULT '',
  created_utc TEXT NOT NULL);
)sql";

// §2.3 calibration health of a camera source against its scan's LiDAR, found at ingest; and the
// visual reference photos kept with scans.
constexpr char kCalibrationTable[] = R"sql(CREATE TABLE calibration(
  camera_source INTEGER PRIMARY KEY,
  lidar_source INTEGER NOT NULL,
  version INTEGER NOT NULL,
  verdict INTEGER NOT NULL,
  points_in_view INTEGER NOT NULL,
  features INTEGER NOT NULL,
  matched INTEGER NOT NULL,
  cell_px REAL NOT NULL,
  pixel_mean_px REAL NOT NULL, pixel_p95_px REAL NOT NULL,
  offset_mean_m REAL NOT NULL, offset_p95_m REAL NOT NULL,
  roundtrip_mean_m REAL NOT NULL, roundtrip_p95_m REAL NOT NULL,
  rotation_deg REAL NOT NULL,
  note TEXT NOT NULL);
CREATE TABLE visual_references(
  scan_id INTEGER NOT NULL REFERENCES scans(id) ON DELETE CASCADE,
  name TEXT NOT NULL,
  qx REAL NOT NULL, qy REAL NOT NULL, qz REAL NOT NULL, qw REAL NOT NULL,
  ox_m REAL NOT NULL, oy_m REAL NOT NULL, oz_m REAL NOT NULL,
  blob_sha256 TEXT NOT NULL,
  width_px INTEGER NOT NULL,
  height_px INTEGER NOT NULL,
  size_bytes INTEGER NOT NULL,
  version INTEGER NOT NULL,
  PRIMARY KEY (scan_id, name));
)sql";

// §9 lens dirt and fog maps of a rig's camera (text: fusion::LensMapToText). Project data, as
// profiles: not versioned, kept through rollbacks.
constexpr char kLensMapsTable[] = R"sql(CREATE TABLE lens_maps(
  id INTEGER PRIMARY KEY,
  rig TEXT NOT NULL,
  camera TEXT NOT NULL,
  body TEXT NOT NULL,
  created_utc TEXT NOT NULL);
)sql";

}  // namespace

absl::Status CreateSchema(Db& db) {
  return db.Exec(absl::StrCat(R"sql(
BEGIN;
CREATE TABLE schema_version(version INTEGER NOT NULL);
INSERT INTO schema_version(version) VALUES ()sql",
                              kCatalogSchemaVersion, R"sql();
CREATE TABLE project(
  id INTEGER PRIMARY KEY CHECK (id = 1),
  name TEXT NOT NULL,
  description TEXT NOT NULL,
  vossel_size_m REAL NOT NULL,
  keep_versions INTEGER NOT NULL,
  tile_vossels INTEGER NOT NULL,
  created_utc TEXT NOT NULL,
  active_profile TEXT NOT NULL DEFAULT 'default',
  origin_fixed INTEGER NOT NULL DEFAULT 0,
  origin_x REAL NOT NULL DEFAULT 0,
  origin_y REAL NOT NULL DEFAULT 0,
  origin_z REAL NOT NULL DEFAULT 0);
CREATE TABLE versions(
  version INTEGER PRIMARY KEY,
  vossel_count INTEGER NOT NULL,
  record_count INTEGER NOT NULL,
  created_utc TEXT NOT NULL,
  made_by TEXT NOT NULL DEFAULT '',
  bytes_written INTEGER NOT NULL DEFAULT 0,
  pinned INTEGER NOT NULL DEFAULT 0,
  pruned INTEGER NOT NULL DEFAULT 0);
CREATE TABLE manifest(
  version INTEGER NOT NULL,
  tx INTEGER NOT NULL, ty INTEGER NOT NULL, tz INTEGER NOT NULL,
  layer TEXT NOT NULL,
  object TEXT NOT NULL,
  vossels INTEGER NOT NULL,
  records INTEGER NOT NULL,
  bytes INTEGER NOT NULL,
  PRIMARY KEY (version, tx, ty, tz, layer));
CREATE TABLE reach(
  version INTEGER NOT NULL,
  source_id INTEGER NOT NULL,
  object TEXT NOT NULL,
  bytes INTEGER NOT NULL,
  PRIMARY KEY (version, source_id));
CREATE TABLE source_tiles(
  source_id INTEGER NOT NULL,
  tx INTEGER NOT NULL, ty INTEGER NOT NULL, tz INTEGER NOT NULL,
  version INTEGER NOT NULL,
  PRIMARY KEY (source_id, tx, ty, tz));
CREATE TABLE scans(
  id INTEGER PRIMARY KEY,
  name TEXT NOT NULL,
  rig TEXT NOT NULL,
  captured_utc TEXT NOT NULL,
  qx REAL NOT NULL, qy REAL NOT NULL, qz REAL NOT NULL, qw REAL NOT NULL,
  ox_m REAL NOT NULL, oy_m REAL NOT NULL, oz_m REAL NOT NULL,
  batch INTEGER NOT NULL,
  version INTEGER NOT NULL,
  deleted_in INTEGER,
  created_utc TEXT NOT NULL);
CREATE TABLE sources(
  id INTEGER PRIMARY KEY,
  scan_id INTEGER NOT NULL REFERENCES scans(id) ON DELETE CASCADE,
  name TEXT NOT NULL,
  modality INTEGER NOT NULL,
  qx REAL NOT NULL, qy REAL NOT NULL, qz REAL NOT NULL, qw REAL NOT NULL,
  ox_m REAL NOT NULL, oy_m REAL NOT NULL, oz_m REAL NOT NULL,
  blob_sha256 TEXT NOT NULL,
  width_px INTEGER NOT NULL,
  height_px INTEGER NOT NULL,
  divergence_rad REAL NOT NULL,
  point_count INTEGER NOT NULL,
  version INTEGER NOT NULL,
  camera TEXT NOT NULL DEFAULT '',
  mask_sha256 TEXT NOT NULL DEFAULT '');
CREATE INDEX sources_by_scan ON sources(scan_id);
)sql",
                              kScanLivesTable, kProfilesTable, kRendersTable, kOperationsTable,
                              kCalibrationTable, kLensMapsTable,
                              R"sql(
CREATE TABLE batches(
  id INTEGER PRIMARY KEY,
  kind TEXT NOT NULL,
  scan_id INTEGER,
  version INTEGER NOT NULL,
  created_utc TEXT NOT NULL);
COMMIT;
)sql"));
}

absl::Status MigrateSchema(Db& db, int64_t from) {
  if (from < 2 || from > kCatalogSchemaVersion) {
    return absl::FailedPreconditionError(
        absl::StrCat("no migration from catalog schema ", from, " to ", kCatalogSchemaVersion));
  }
  // Each step takes the catalog one schema forward.
  const std::string steps[] = {
      // 2 → 3: weighting profiles and the active profile.
      absl::StrCat(kProfilesTable,
                   "ALTER TABLE project ADD COLUMN active_profile TEXT NOT NULL DEFAULT 'default';\n"),
      // 3 → 4: the spans of versions each scan is live in.
      absl::StrCat(kScanLivesTable,
                   "INSERT INTO scan_lives(scan_id, from_version, to_version) "
                   "SELECT id, version, deleted_in FROM scans;\n"
                   "DROP INDEX IF EXISTS live_scan_names;\n"),
      // 4 → 5: renders, to be cited by what comes back.
      kRendersTable,
      // 5 → 6: the projection of a derived source.
      "ALTER TABLE sources ADD COLUMN camera TEXT NOT NULL DEFAULT '';\n",
      // 6 → 7: changes asked for under a request id.
      kOperationsTable,
      // 7 → 8: the project's origin; a project with scans worked in world coordinates (0).
      "ALTER TABLE project ADD COLUMN origin_fixed INTEGER NOT NULL DEFAULT 0;\n"
      "ALTER TABLE project ADD COLUMN origin_x REAL NOT NULL DEFAULT 0;\n"
      "ALTER TABLE project ADD COLUMN origin_y REAL NOT NULL DEFAULT 0;\n"
      "ALTER TABLE project ADD COLUMN origin_z REAL NOT NULL DEFAULT 0;\n"
      "UPDATE project SET origin_fixed = 1 WHERE EXISTS (SELECT 1 FROM scans);\n",
      // 8 → 9: calibration health of cameras, visual references of scans.
      kCalibrationTable,
      // 9 → 10: lens dirt and fog maps.
      kLensMapsTable,
      // 10 → 11: a camera's mask image.
      "ALTER TABLE sources ADD COLUMN mask_sha256 TEXT NOT NULL DEFAULT '';\n"};
  std::string sql = "BEGIN IMMEDIATE;\n";
  for (int64_t v = from; v < kCatalogSchemaVersion; ++v) sql += steps[v - 2];
  absl::StrAppend(&sql, "UPDATE schema_version SET version = ", kCatalogSchemaVersion, ";\nCOMMIT;\n");
  absl::Status s = db.Exec(sql);
  if (!s.ok()) db.Exec("ROLLBACK;").IgnoreError();
  return s;
}

absl::Status DropRowsNewerThan(Db& db, int64_t head) {
  if (absl::Status s = db.Exec("BEGIN IMMEDIATE;"); !s.ok()) return s;
  for (const char* sql : {"DELETE FROM manifest WHERE version > ?1",
                          "DELETE FROM reach WHERE version > ?1",
                          "DELETE FROM source_tiles WHERE version > ?1",
                          "UPDATE scans SET deleted_in = NULL WHERE deleted_in > ?1",
                          "UPDATE scan_lives SET to_version = NULL WHERE to_version > ?1",
                          "DELETE FROM scan_lives WHERE from_version > ?1",
                          "DELETE FROM sources WHERE version > ?1",
                          "DELETE FROM calibration WHERE version > ?1",
                          "DELETE FROM visual_references WHERE version > ?1",
                          "DELETE FROM scans WHERE version > ?1",
                          "DELETE FROM batches WHERE version > ?1",
                          "DELETE FROM operations WHERE version > ?1",
                          "DELETE FROM versions WHERE version > ?1"}) {
    absl::StatusOr<Stmt> stmt = db.Prepare(sql);
    absl::Status s = stmt.ok() ? stmt->Bind(1, head).Run() : stmt.status();
    if (!s.ok()) {
      db.Exec("ROLLBACK;").IgnoreError();
      return s;
    }
  }
  return db.Exec("COMMIT;");
}

}  // namespace vasl::store::internal

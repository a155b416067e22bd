// The project store (project_store.h): directory layout, atomic commit, crash recovery,
// retention (ARCHITECTURE.md "Storage of one project").
#include "lattice/store/project_store.h"

#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cmath>
#include <map>
#include <mutex>
#include <optional>
#include <system_error>
#include <utility>

#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/strip.h"
#include "lattice/records/record_grid.h"
#include "lattice/store/catalog.h"
#include "lattice/store/fs_util.h"

namespace vasl::store {
namespace fs = std::filesystem;
using internal::Db;
using internal::Stmt;

namespace {

constexpr char kCatalogFile[] = "catalog.sqlite";
constexpr char kHeadFile[] = "HEAD";
constexpr char kBlobsDir[] = "blobs";
constexpr char kVersionsDir[] = "versions";
constexpr char kTmpPrefix[] = ".tmp-";
constexpr char kGeometryFile[] = "geometry.vdb";
constexpr char kRecordsFile[] = "records.vdb";
constexpr char kFusedFile[] = "fused-default.vdb";

absl::Status ValidateProjectName(const std::string& name) {
  bool ok = !name.empty() && name.size() <= 63 && absl::ascii_isalnum(name[0]);
  for (char c : name) {
    ok = ok && ((c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '.' || c == '_' ||
                c == '-');
  }
  if (!ok) {
    return absl::InvalidArgumentError(absl::StrCat(
        "invalid project name \"", name,
        "\": use 1-63 characters of [a-z0-9._-], starting with a letter or digit"));
  }
  return absl::OkStatus();
}

bool IsSha256Hex(const std::string& s) {
  if (s.size() != 64) return false;
  for (char c : s) {
    if (!((c >= '0' && c <= '9') || (c >= 'a' && c <= 'f'))) return false;
  }
  return true;
}

/// Parses a non-negative version number written as decimal digits (HEAD, versions/<n>).
std::optional<int64_t> ParseVersion(std::string_view raw) {
  const absl::string_view text =
      absl::StripAsciiWhitespace(absl::string_view(raw.data(), raw.size()));
  int64_t v = 0;
  if (text.empty() || !std::all_of(text.begin(), text.end(), absl::ascii_isdigit) ||
      !absl::SimpleAtoi(text, &v)) {
    return std::nullopt;
  }
  return v;
}

absl::Status RemoveAll(const fs::path& p) {
  std::error_code ec;
  fs::remove_all(p, ec);
  if (ec) return internal::ErrnoError("cannot remove", p, ec.value());
  return absl::OkStatus();
}

// Binds a pose as (qx, qy, qz, qw, ox, oy, oz) starting at parameter `first`.
void BindPose(Stmt& st, int first, const geometry::Pose& p) {
  const Eigen::Quaterniond& q = p.q_world_sensor;
  st.Bind(first, q.x()).Bind(first + 1, q.y()).Bind(first + 2, q.z()).Bind(first + 3, q.w());
  st.Bind(first + 4, p.o_world.x()).Bind(first + 5, p.o_world.y()).Bind(first + 6, p.o_world.z());
}
geometry::Pose ColumnPose(const Stmt& st, int first) {
  geometry::Pose p;
  p.q_world_sensor = Eigen::Quaterniond(st.Real(first + 3), st.Real(first), st.Real(first + 1),
                                        st.Real(first + 2));
  p.o_world = Eigen::Vector3d(st.Real(first + 4), st.Real(first + 5), st.Real(first + 6));
  return p;
}

}  // namespace

struct ProjectStore::Impl {
  fs::path dir;
  std::string name;
  ProjectSettings settings;
  std::string created_utc;
  std::atomic<int64_t> head{0};

  mutable std::mutex db_mu;  ///< guards `db` (statements are short)
  Db db;
  std::mutex commit_mu;  ///< one commit at a time

  CommitStage fault_stage = CommitStage::kNone;
  bool fault_crash = false;

  explicit Impl(Db d) : db(std::move(d)) {}

  fs::path versions_dir() const { return dir / kVersionsDir; }
  fs::path version_dir(int64_t v) const { return versions_dir() / std::to_string(v); }

  /// Brings disk and catalog back to HEAD: drops catalog rows newer than HEAD, deletes temp
  /// dirs/files and version dirs newer than HEAD.
  absl::Status RecoverToHead(int64_t head_version) {
    {
      std::lock_guard<std::mutex> lock(db_mu);
      if (absl::Status s = internal::DropRowsNewerThan(db, head_version); !s.ok()) return s;
    }
    std::error_code ec;
    for (const fs::directory_entry& e : fs::directory_iterator(versions_dir(), ec)) {
      const std::string n = e.path().filename().string();
      const std::optional<int64_t> v = ParseVersion(n);
      if (absl::StartsWith(n, kTmpPrefix) || (v && *v > head_version)) {
        if (absl::Status s = RemoveAll(e.path()); !s.ok()) return s;
      }
    }
    if (ec) return internal::ErrnoError("cannot list", versions_dir(), ec.value());
    for (const fs::path& d : {dir / kBlobsDir, dir}) {
      for (const fs::directory_entry& e : fs::directory_iterator(d, ec)) {
        const std::string n = e.path().filename().string();
        if (absl::StartsWith(n, kTmpPrefix) || absl::StartsWith(n, ".HEAD.tmp-")) {
          if (absl::Status s = RemoveAll(e.path()); !s.ok()) return s;
        }
      }
    }
    return internal::FsyncPath(versions_dir());
  }

  /// Retention: keeps HEAD and the `keep_versions` versions before it; older version dirs are
  /// deleted and their catalog rows marked pruned. Best effort: a failure here leaves extra
  /// versions on disk, which the next commit prunes again.
  void Prune(int64_t head_version) {
    const int64_t oldest_kept = head_version - std::max(0, settings.keep_versions);
    std::error_code ec;
    for (const fs::directory_entry& e : fs::directory_iterator(versions_dir(), ec)) {
      const std::optional<int64_t> v = ParseVersion(e.path().filename().string());
      if (v && *v < oldest_kept) RemoveAll(e.path()).IgnoreError();
    }
    internal::FsyncPath(versions_dir()).IgnoreError();
    std::lock_guard<std::mutex> lock(db_mu);
    absl::StatusOr<Stmt> st = db.Prepare("UPDATE versions SET pruned = 1 WHERE version < ?1");
    if (st.ok()) st->Bind(1, oldest_kept).Run().IgnoreError();
  }
};

ProjectStore::ProjectStore(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
ProjectStore::~ProjectStore() = default;

absl::StatusOr<std::unique_ptr<ProjectStore>> ProjectStore::Create(
    const fs::path& dir, const std::string& name, const ProjectSettings& settings) {
  if (absl::Status s = ValidateProjectName(name); !s.ok()) return s;
  if (!(settings.vossel_size_m > 0.0) || !std::isfinite(settings.vossel_size_m)) {
    return absl::InvalidArgumentError(absl::StrCat("vossel size must be a positive length in "
                                                   "metres; got ",
                                                   settings.vossel_size_m));
  }
  if (settings.keep_versions < 0) {
    return absl::InvalidArgumentError(absl::StrCat("keep_versions must be >= 0; got ",
                                                   settings.keep_versions));
  }
  std::error_code ec;
  if (fs::exists(dir, ec)) {
    return absl::AlreadyExistsError(absl::StrCat("project directory ", dir.string(),
                                                 " already exists"));
  }
  // Build the project in a temp dir beside it, then rename: a crash never leaves half a
  // project under the real name.
  const fs::path parent = dir.parent_path().empty() ? fs::path(".") : dir.parent_path();
  const fs::path tmp =
      parent / absl::StrCat(kTmpPrefix, "create-", dir.filename().string(), "-",
                            internal::RandomHex(12));
  auto fail = [&](absl::Status s) {
    RemoveAll(tmp).IgnoreError();
    return s;
  };
  fs::create_directories(tmp / kBlobsDir, ec);
  if (!ec) fs::create_directories(tmp / kVersionsDir, ec);
  if (ec) return fail(internal::ErrnoError("cannot create", tmp, ec.value()));
  {
    absl::StatusOr<Db> db = Db::Open(tmp / kCatalogFile, /*create=*/true);
    if (!db.ok()) return fail(db.status());
    if (absl::Status s = internal::CreateSchema(*db); !s.ok()) return fail(s);
    absl::StatusOr<Stmt> st = db->Prepare(
        "INSERT INTO project(id, name, description, vossel_size_m, keep_versions, created_utc) "
        "VALUES (1, ?1, ?2, ?3, ?4, ?5)");
    if (!st.ok()) return fail(st.status());
    st->Bind(1, name).Bind(2, settings.description).Bind(3, settings.vossel_size_m);
    st->Bind(4, int64_t{settings.keep_versions}).Bind(5, internal::UtcNowIso8601());
    if (absl::Status s = st->Run(); !s.ok()) return fail(s);
  }  // connection closed: the WAL is checkpointed before the rename
  for (absl::Status s : {internal::WriteFileDurable(tmp / kHeadFile, "0\n"),
                         internal::FsyncPath(tmp / kCatalogFile), internal::FsyncPath(tmp / kBlobsDir),
                         internal::FsyncPath(tmp / kVersionsDir), internal::FsyncPath(tmp)}) {
    if (!s.ok()) return fail(s);
  }
  fs::rename(tmp, dir, ec);
  if (ec) {
    if (ec == std::errc::file_exists || ec == std::errc::directory_not_empty) {
      return fail(absl::AlreadyExistsError(
          absl::StrCat("project directory ", dir.string(), " already exists")));
    }
    return fail(internal::ErrnoError("cannot rename project into place at", dir, ec.value()));
  }
  if (absl::Status s = internal::FsyncPath(parent); !s.ok()) return s;
  return Open(dir);
}

absl::StatusOr<std::unique_ptr<ProjectStore>> ProjectStore::Open(const fs::path& dir) {
  std::error_code ec;
  if (!fs::is_directory(dir, ec) || !fs::is_regular_file(dir / kCatalogFile, ec) ||
      !fs::is_regular_file(dir / kHeadFile, ec)) {
    return absl::NotFoundError(absl::StrCat(
        "no project at ", dir.string(), " (a project directory holds catalog.sqlite and HEAD)"));
  }
  absl::StatusOr<std::string> head_text = internal::ReadWholeFile(dir / kHeadFile);
  if (!head_text.ok()) return head_text.status();
  const std::optional<int64_t> head = ParseVersion(*head_text);
  if (!head) {
    return absl::DataLossError(absl::StrCat((dir / kHeadFile).string(),
                                            " does not hold a version number: \"",
                                            head_text->substr(0, 40), "\""));
  }
  absl::StatusOr<Db> db = Db::Open(dir / kCatalogFile, /*create=*/false);
  if (!db.ok()) return db.status();
  auto impl = std::make_unique<Impl>(std::move(*db));
  impl->dir = dir;
  impl->head = *head;
  {
    absl::StatusOr<Stmt> st = impl->db.Prepare("SELECT MAX(version) FROM schema_version");
    if (!st.ok()) return st.status();
    absl::StatusOr<bool> row = st->Step();
    if (!row.ok()) return row.status();
    if (!*row || st->Int(0) > internal::kCatalogSchemaVersion) {
      return absl::FailedPreconditionError(absl::StrCat(
          "catalog ", (dir / kCatalogFile).string(), " has schema version ", *row ? st->Int(0) : 0,
          "; this build reads up to ", internal::kCatalogSchemaVersion, ": upgrade vasl"));
    }
  }
  {
    absl::StatusOr<Stmt> st = impl->db.Prepare(
        "SELECT name, description, vossel_size_m, keep_versions, created_utc FROM project "
        "WHERE id = 1");
    if (!st.ok()) return st.status();
    absl::StatusOr<bool> row = st->Step();
    if (!row.ok()) return row.status();
    if (!*row) {
      return absl::DataLossError(
          absl::StrCat("catalog ", (dir / kCatalogFile).string(), " has no project row"));
    }
    impl->name = st->Text(0);
    impl->settings.description = st->Text(1);
    impl->settings.vossel_size_m = st->Real(2);
    impl->settings.keep_versions = static_cast<int>(st->Int(3));
    impl->created_utc = st->Text(4);
  }
  // HEAD is the truth: anything newer is the debris of an interrupted commit.
  if (absl::Status s = impl->RecoverToHead(*head); !s.ok()) return s;
  return std::unique_ptr<ProjectStore>(new ProjectStore(std::move(impl)));
}

const std::string& ProjectStore::name() const { return impl_->name; }
const ProjectSettings& ProjectStore::settings() const { return impl_->settings; }
const std::string& ProjectStore::created_utc() const { return impl_->created_utc; }
const fs::path& ProjectStore::dir() const { return impl_->dir; }
int64_t ProjectStore::head_version() const { return impl_->head.load(); }

absl::StatusOr<VersionInfo> ProjectStore::HeadInfo() const {
  VersionInfo info;
  info.version = impl_->head.load();
  if (info.version == 0) return info;
  std::lock_guard<std::mutex> lock(impl_->db_mu);
  absl::StatusOr<Stmt> st = impl_->db.Prepare(
      "SELECT vossel_count, record_count, created_utc FROM versions WHERE version = ?1");
  if (!st.ok()) return st.status();
  st->Bind(1, info.version);
  absl::StatusOr<bool> row = st->Step();
  if (!row.ok()) return row.status();
  if (!*row) {
    return absl::DataLossError(absl::StrCat("catalog has no row for HEAD version ",
                                            info.version, " of project ", impl_->name));
  }
  info.vossel_count = st->Int(0);
  info.record_count = st->Int(1);
  info.created_utc = st->Text(2);
  return info;
}

absl::StatusOr<std::string> ProjectStore::PutBlob(std::string_view bytes) {
  absl::StatusOr<std::string> sha = internal::Sha256Hex(bytes);
  if (!sha.ok()) return sha.status();
  const fs::path blobs = impl_->dir / kBlobsDir;
  const fs::path path = blobs / *sha;
  std::error_code ec;
  // Content-addressed: an existing blob of the right size already holds these bytes.
  if (fs::is_regular_file(path, ec) && fs::file_size(path, ec) == bytes.size() && !ec) {
    return *sha;
  }
  const fs::path tmp = blobs / absl::StrCat(kTmpPrefix, *sha, "-", internal::RandomHex(8));
  if (absl::Status s = internal::WriteFileDurable(tmp, bytes); !s.ok()) {
    ::unlink(tmp.c_str());
    return s;
  }
  if (::rename(tmp.c_str(), path.c_str()) != 0) {
    const int err = errno;
    ::unlink(tmp.c_str());
    return internal::ErrnoError("cannot rename blob into place at", path, err);
  }
  if (absl::Status s = internal::FsyncPath(blobs); !s.ok()) return s;
  return *sha;
}

absl::StatusOr<std::string> ProjectStore::ReadBlob(const std::string& sha256) const {
  if (!IsSha256Hex(sha256)) {
    return absl::InvalidArgumentError(
        absl::StrCat("\"", sha256, "\" is not a blob id (64 lowercase hex characters)"));
  }
  absl::StatusOr<std::string> bytes = internal::ReadWholeFile(impl_->dir / kBlobsDir / sha256);
  if (absl::IsNotFound(bytes.status())) {
    return absl::NotFoundError(
        absl::StrCat("no blob ", sha256, " in project ", impl_->name));
  }
  return bytes;
}

absl::StatusOr<std::vector<ScanInfo>> ProjectStore::ListScans() const {
  const int64_t head = impl_->head.load();
  std::lock_guard<std::mutex> lock(impl_->db_mu);
  std::vector<ScanInfo> scans;
  std::map<int64_t, size_t> by_id;
  {
    absl::StatusOr<Stmt> st = impl_->db.Prepare(
        "SELECT id, name, rig, captured_utc, qx, qy, qz, qw, ox_m, oy_m, oz_m, batch, version, "
        "created_utc FROM scans WHERE version <= ?1 ORDER BY id");
    if (!st.ok()) return st.status();
    st->Bind(1, head);
    for (;;) {
      absl::StatusOr<bool> row = st->Step();
      if (!row.ok()) return row.status();
      if (!*row) break;
      ScanInfo s;
      s.id = st->Int(0);
      s.name = st->Text(1);
      s.rig = st->Text(2);
      s.captured_utc = st->Text(3);
      s.pose = ColumnPose(*st, 4);
      s.batch = static_cast<int32_t>(st->Int(11));
      s.version = st->Int(12);
      s.created_utc = st->Text(13);
      by_id[s.id] = scans.size();
      scans.push_back(std::move(s));
    }
  }
  absl::StatusOr<Stmt> st = impl_->db.Prepare(
      "SELECT id, scan_id, name, modality, qx, qy, qz, qw, ox_m, oy_m, oz_m, blob_sha256, "
      "width_px, height_px, divergence_rad, point_count FROM sources WHERE version <= ?1 "
      "ORDER BY id");
  if (!st.ok()) return st.status();
  st->Bind(1, head);
  for (;;) {
    absl::StatusOr<bool> row = st->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    SourceInfo src;
    src.id = static_cast<int32_t>(st->Int(0));
    src.scan_id = st->Int(1);
    src.name = st->Text(2);
    src.modality = static_cast<records::Modality>(st->Int(3));
    src.pose = ColumnPose(*st, 4);
    src.blob_sha256 = st->Text(11);
    src.width_px = static_cast<int>(st->Int(12));
    src.height_px = static_cast<int>(st->Int(13));
    src.divergence_rad = st->Real(14);
    src.point_count = st->Int(15);
    auto it = by_id.find(src.scan_id);
    if (it != by_id.end()) scans[it->second].sources.push_back(std::move(src));
  }
  return scans;
}

absl::StatusOr<bool> ProjectStore::HasScan(const std::string& name) const {
  std::lock_guard<std::mutex> lock(impl_->db_mu);
  absl::StatusOr<Stmt> st = impl_->db.Prepare("SELECT 1 FROM scans WHERE name = ?1");
  if (!st.ok()) return st.status();
  st->Bind(1, name);
  return st->Step();
}

absl::StatusOr<int32_t> ProjectStore::NextSourceId() const {
  std::lock_guard<std::mutex> lock(impl_->db_mu);
  absl::StatusOr<Stmt> st = impl_->db.Prepare("SELECT COALESCE(MAX(id), 0) + 1 FROM sources");
  if (!st.ok()) return st.status();
  absl::StatusOr<bool> row = st->Step();
  if (!row.ok()) return row.status();
  return static_cast<int32_t>(st->Int(0));
}

absl::StatusOr<int32_t> ProjectStore::NextBatchId() const {
  std::lock_guard<std::mutex> lock(impl_->db_mu);
  absl::StatusOr<Stmt> st = impl_->db.Prepare(
      "SELECT MAX(COALESCE((SELECT MAX(id) FROM batches), 0), "
      "COALESCE((SELECT MAX(batch) FROM scans), 0)) + 1");
  if (!st.ok()) return st.status();
  absl::StatusOr<bool> row = st->Step();
  if (!row.ok()) return row.status();
  return static_cast<int32_t>(st->Int(0));
}

absl::StatusOr<std::shared_ptr<const Snapshot>> ProjectStore::LoadSnapshot(int64_t version) const {
  if (version < 0) {
    return absl::InvalidArgumentError(absl::StrCat("version must be >= 0; got ", version));
  }
  auto snap = std::make_shared<Snapshot>();
  snap->version = version;
  snap->fused.profile = "default";
  if (version == 0) {
    snap->geometry.vossel_size_m = impl_->settings.vossel_size_m;
    snap->geometry.index_grid = openvdb::Int32Grid::create(-1);
    snap->geometry.index_grid->setTransform(
        openvdb::math::Transform::createLinearTransform(impl_->settings.vossel_size_m));
    snap->geometry.index_grid->setName("index");
    snap->geometry.index_grid->setGridClass(openvdb::GRID_UNKNOWN);
    return std::shared_ptr<const Snapshot>(std::move(snap));
  }
  absl::StatusOr<fs::path> dir = VersionDir(version);
  if (!dir.ok()) return dir.status();
  absl::StatusOr<records::VosselGeometry> geometry = records::ReadGeometry(*dir / kGeometryFile);
  if (!geometry.ok()) return geometry.status();
  snap->geometry = std::move(*geometry);
  absl::StatusOr<records::RecordSet> recs = records::ReadRecords(snap->geometry,
                                                                 *dir / kRecordsFile);
  if (!recs.ok()) return recs.status();
  snap->records = std::move(*recs);
  std::error_code ec;
  if (fs::exists(*dir / kFusedFile, ec)) {
    absl::StatusOr<records::FusedValues> fused =
        records::ReadFused(snap->geometry, *dir / kFusedFile);
    if (!fused.ok()) return fused.status();
    snap->fused = std::move(*fused);
  }
  return std::shared_ptr<const Snapshot>(std::move(snap));
}

absl::StatusOr<int64_t> ProjectStore::CommitScan(const Snapshot& snapshot, const ScanInfo& scan) {
  Impl& im = *impl_;
  std::lock_guard<std::mutex> commit_lock(im.commit_mu);
  const CommitStage fault = std::exchange(im.fault_stage, CommitStage::kNone);
  const bool crash = im.fault_crash;
  auto injected = [&](CommitStage stage) { return fault == stage; };
  auto injected_error = [](const char* where) {
    return absl::InternalError(absl::StrCat("injected commit failure after ", where));
  };

  // Bad input never changes the project: validate everything before writing.
  if (scan.name.empty()) return absl::InvalidArgumentError("scan name must not be empty");
  absl::StatusOr<bool> exists = HasScan(scan.name);
  if (!exists.ok()) return exists.status();
  if (*exists) {
    return absl::AlreadyExistsError(absl::StrCat("scan \"", scan.name,
                                                 "\" already exists in project ", im.name));
  }
  if (std::fabs(snapshot.geometry.vossel_size_m - im.settings.vossel_size_m) >
      1e-9 * im.settings.vossel_size_m) {
    return absl::InvalidArgumentError(
        absl::StrCat("snapshot vossel size ", snapshot.geometry.vossel_size_m,
                     " m differs from the project's ", im.settings.vossel_size_m, " m"));
  }
  {
    std::lock_guard<std::mutex> lock(im.db_mu);
    for (const SourceInfo& src : scan.sources) {
      absl::StatusOr<Stmt> st = im.db.Prepare("SELECT 1 FROM sources WHERE id = ?1");
      if (!st.ok()) return st.status();
      st->Bind(1, int64_t{src.id});
      absl::StatusOr<bool> row = st->Step();
      if (!row.ok()) return row.status();
      if (*row) {
        return absl::AlreadyExistsError(absl::StrCat(
            "source id ", src.id, " is already used in project ", im.name,
            "; take ids from NextSourceId()"));
      }
    }
  }

  const int64_t head = im.head.load();
  const int64_t version = head + 1;
  const fs::path final_dir = im.version_dir(version);
  const fs::path tmp = im.versions_dir() /
                       absl::StrCat(kTmpPrefix, version, "-", internal::RandomHex(12));
  bool catalog_committed = false;
  // Undo of a failed commit (not after a simulated crash): HEAD still names `head`.
  auto fail = [&](absl::Status s) {
    RemoveAll(tmp).IgnoreError();
    RemoveAll(final_dir).IgnoreError();
    if (catalog_committed) {
      std::lock_guard<std::mutex> lock(im.db_mu);
      internal::DropRowsNewerThan(im.db, head).IgnoreError();
    }
    internal::FsyncPath(im.versions_dir()).IgnoreError();
    return s;
  };

  // 1. The version's files, in a temp dir, fsynced.
  std::error_code ec;
  RemoveAll(final_dir).IgnoreError();  // debris of an earlier failed attempt, never committed
  fs::create_directory(tmp, ec);
  if (ec) return fail(internal::ErrnoError("cannot create", tmp, ec.value()));
  for (absl::Status s :
       {records::WriteGeometry(snapshot.geometry, tmp / kGeometryFile),
        records::WriteRecords(snapshot.geometry, snapshot.records, tmp / kRecordsFile),
        records::WriteFused(snapshot.geometry, snapshot.fused, tmp / kFusedFile),
        internal::FsyncDirectoryTree(tmp)}) {
    if (!s.ok()) return fail(s);
  }
  if (injected(CommitStage::kAfterFiles)) {
    return crash ? injected_error("files") : fail(injected_error("files"));
  }

  // 2. Rename into place; versions/<n> is invisible to readers until HEAD names it.
  if (::rename(tmp.c_str(), final_dir.c_str()) != 0) {
    return fail(internal::ErrnoError("cannot rename version into place at", final_dir, errno));
  }
  if (absl::Status s = internal::FsyncPath(im.versions_dir()); !s.ok()) return fail(s);
  if (injected(CommitStage::kAfterVersionRename)) {
    return crash ? injected_error("version rename") : fail(injected_error("version rename"));
  }

  // 3. Catalog rows, one transaction.
  {
    std::lock_guard<std::mutex> lock(im.db_mu);
    const std::string now = internal::UtcNowIso8601();
    absl::Status s = im.db.Exec("BEGIN IMMEDIATE;");
    auto run = [&](std::string_view sql, auto&& bind) -> absl::Status {
      if (!s.ok()) return s;
      absl::StatusOr<Stmt> st = im.db.Prepare(sql);
      if (!st.ok()) return st.status();
      bind(*st);
      return st->Run();
    };
    s = run("INSERT INTO versions(version, vossel_count, record_count, created_utc) "
            "VALUES (?1, ?2, ?3, ?4)",
            [&](Stmt& st) {
              st.Bind(1, version).Bind(2, int64_t(snapshot.geometry.size()));
              st.Bind(3, int64_t(snapshot.records.size())).Bind(4, now);
            });
    s = run("INSERT INTO scans(name, rig, captured_utc, qx, qy, qz, qw, ox_m, oy_m, oz_m, "
            "batch, version, created_utc) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, "
            "?11, ?12, ?13)",
            [&](Stmt& st) {
              st.Bind(1, scan.name).Bind(2, scan.rig).Bind(3, scan.captured_utc);
              BindPose(st, 4, scan.pose);
              st.Bind(11, int64_t{scan.batch}).Bind(12, version).Bind(13, now);
            });
    int64_t scan_id = 0;
    if (s.ok()) {
      absl::StatusOr<Stmt> st = im.db.Prepare("SELECT id FROM scans WHERE name = ?1");
      absl::StatusOr<bool> row = st.ok() ? st->Bind(1, scan.name).Step() : st.status();
      if (!row.ok()) s = row.status();
      else if (*row) scan_id = st->Int(0);
    }
    for (const SourceInfo& src : scan.sources) {
      s = run("INSERT INTO sources(id, scan_id, name, modality, qx, qy, qz, qw, ox_m, oy_m, "
              "oz_m, blob_sha256, width_px, height_px, divergence_rad, point_count, version) "
              "VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15, ?16, "
              "?17)",
              [&](Stmt& st) {
                st.Bind(1, int64_t{src.id}).Bind(2, scan_id).Bind(3, src.name);
                st.Bind(4, int64_t{static_cast<int>(src.modality)});
                BindPose(st, 5, src.pose);
                st.Bind(12, src.blob_sha256).Bind(13, int64_t{src.width_px});
                st.Bind(14, int64_t{src.height_px}).Bind(15, src.divergence_rad);
                st.Bind(16, src.point_count).Bind(17, version);
              });
    }
    s = run("INSERT OR IGNORE INTO batches(id, kind, scan_id, version, created_utc) "
            "VALUES (?1, 'ingest', ?2, ?3, ?4)",
            [&](Stmt& st) {
              st.Bind(1, int64_t{scan.batch}).Bind(2, scan_id).Bind(3, version).Bind(4, now);
            });
    if (s.ok()) s = im.db.Exec("COMMIT;");
    if (!s.ok()) {
      im.db.Exec("ROLLBACK;").IgnoreError();
      if (absl::IsAlreadyExists(s)) {
        s = absl::AlreadyExistsError(absl::StrCat("scan \"", scan.name, "\" or one of its "
                                                  "source ids already exists in project ",
                                                  im.name, " (", s.message(), ")"));
      }
    }
    if (!s.ok()) {
      // Not yet committed: nothing to drop in the catalog.
      RemoveAll(final_dir).IgnoreError();
      internal::FsyncPath(im.versions_dir()).IgnoreError();
      return s;
    }
    catalog_committed = true;
  }
  if (injected(CommitStage::kAfterCatalog)) {
    return crash ? injected_error("catalog") : fail(injected_error("catalog"));
  }

  // 4. HEAD, atomically: the commit point.
  if (absl::Status s = internal::ReplaceFileAtomically(im.dir / kHeadFile,
                                                       absl::StrCat(version, "\n"));
      !s.ok()) {
    // If the rename itself happened, HEAD names the new version: it is committed.
    absl::StatusOr<std::string> text = internal::ReadWholeFile(im.dir / kHeadFile);
    if (!text.ok() || ParseVersion(*text) != version) return fail(s);
  }
  im.head = version;
  im.Prune(version);
  return version;
}

absl::StatusOr<fs::path> ProjectStore::VersionDir(int64_t version) const {
  const int64_t head = impl_->head.load();
  if (version <= 0 || version > head) {
    return absl::NotFoundError(absl::StrCat("project ", impl_->name, " has no version ", version,
                                            " on disk (HEAD is ", head,
                                            "; version 0 is the empty project)"));
  }
  const fs::path dir = impl_->version_dir(version);
  std::error_code ec;
  if (!fs::is_directory(dir, ec)) {
    return absl::NotFoundError(absl::StrCat("version ", version, " of project ", impl_->name,
                                            " was pruned by retention (keep_versions = ",
                                            impl_->settings.keep_versions, ", HEAD is ", head,
                                            ")"));
  }
  return dir;
}

absl::StatusOr<std::vector<records::AttributeInfo>> ProjectStore::InspectRecords(
    int64_t version) const {
  absl::StatusOr<fs::path> dir = VersionDir(version);
  if (!dir.ok()) return dir.status();
  return records::ListRecordAttributes(*dir / kRecordsFile);
}

void ProjectStore::InjectCommitFailureForTesting(CommitStage stage, bool simulate_crash) {
  std::lock_guard<std::mutex> lock(impl_->commit_mu);
  impl_->fault_stage = stage;
  impl_->fault_crash = simulate_crash;
}

}  // namespace vasl::store

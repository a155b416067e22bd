// The project store (project_store.h): directory layout, atomic commit, crash recovery,
// retention (ARCHITECTURE.md "Storage of one project").
#include "lattice/store/project_store.h"

#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <map>
#include <mutex>
#include <numeric>
#include <optional>
#include <system_error>
#include <utility>

#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/match.h"
#include "absl/strings/escaping.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/strip.h"
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_pipeline.h>
#include <tbb/task_arena.h>

#include "lattice/records/record_grid.h"
#include "lattice/tiles/tile_split.h"
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
constexpr char kObjectsDir[] = "objects";
constexpr char kTmpPrefix[] = ".tmp-";


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

/// Runs `sql` with `bind` applied; for statements without result rows.
template <typename Bind>
absl::Status RunSql(Db& db, std::string_view sql, Bind&& bind) {
  absl::StatusOr<Stmt> st = db.Prepare(sql);
  if (!st.ok()) return st.status();
  bind(*st);
  return st->Run();
}

/// The records layer's entry of a tile (zeros when it has none).
ManifestEntry RecordsOf(const std::map<std::string, ManifestEntry>& layers) {
  auto it = layers.find(kLayerRecords);
  return it == layers.end() ? ManifestEntry{} : it->second;
}

/// The tiles of version `version`'s `manifest` (`only_tiles`: just those) read from `objects`
/// with the fused layers `profile_layers` and, `with_records`, their records, and put together
/// (tiles::TileAssembler). Tiles are read in parallel, a few at a time, and each is appended
/// to the version's arrays and freed as it arrives: a load holds the version once, not twice.
absl::StatusOr<tiles::Assembled> ReadTiles(const ObjectStore& objects, double vossel_size_m,
                                           int64_t version, const Manifest& manifest,
                                           const std::set<tiles::TileKey>* only_tiles,
                                           const std::vector<std::string>& profile_layers,
                                           bool with_records) {
  std::vector<std::pair<tiles::TileKey, const std::map<std::string, ManifestEntry>*>> todo;
  for (const auto& [key, layers] : manifest.tiles) {
    if (only_tiles == nullptr || only_tiles->count(key) != 0) todo.emplace_back(key, &layers);
  }
  size_t vossels = 0, record_count = 0;
  for (const auto& [key, layers] : todo) {
    vossels += size_t(RecordsOf(*layers).vossels);
    if (with_records) record_count += size_t(RecordsOf(*layers).records);
  }
  tiles::TileAssembler assembler(vossel_size_m, vossels, record_count);
  absl::Status failed;
  auto load = [&](size_t t, tiles::TileContents& tile) -> absl::Status {
    tile.key = todo[t].first;
    const auto& layers = *todo[t].second;
    auto path_of = [&](const char* layer) -> absl::StatusOr<fs::path> {
      auto it = layers.find(layer);
      if (it == layers.end()) {
        return absl::DataLossError(absl::StrCat("version ", version, " tile ",
                                                tiles::ToString(tile.key), " has no ", layer));
      }
      return objects.LocalPath(it->second.object);
    };
    absl::StatusOr<fs::path> g = path_of(kLayerGeometry);
    absl::StatusOr<fs::path> rec = path_of(kLayerRecords);
    absl::StatusOr<fs::path> fu = path_of(kLayerFusedDefault);
    for (const auto* p : {&g, &rec, &fu}) {
      if (!p->ok()) return p->status();
    }
    absl::StatusOr<records::VosselGeometry> geometry = records::ReadGeometry(*g);
    if (!geometry.ok()) return geometry.status();
    tile.geometry = std::move(*geometry);
    if (with_records) {
      absl::StatusOr<records::RecordSet> recs = records::ReadRecords(tile.geometry, *rec);
      if (!recs.ok()) return recs.status();
      tile.records = std::move(*recs);
    }
    absl::StatusOr<records::FusedValues> fused = records::ReadFused(tile.geometry, *fu);
    if (!fused.ok()) return fused.status();
    tile.fused = std::move(*fused);
    for (const std::string& layer : profile_layers) {
      absl::StatusOr<fs::path> path = path_of(layer.c_str());
      absl::StatusOr<records::FusedValues> values =
          path.ok() ? records::ReadFused(tile.geometry, *path) : path.status();
      if (!values.ok()) {
        return absl::IsDataLoss(values.status()) && !path.ok()
                   ? absl::NotFoundError(values.status().message())
                   : values.status();
      }
      tile.profile_fused[layer] = std::move(*values);
    }
    return absl::OkStatus();
  };
  struct Loaded {
    tiles::TileContents tile;
    absl::Status status;
  };
  size_t next = 0;
  tbb::parallel_pipeline(
      size_t(2 * std::max(1, tbb::this_task_arena::max_concurrency())),
      tbb::make_filter<void, size_t>(tbb::filter_mode::serial_in_order,
                                     [&](tbb::flow_control& fc) -> size_t {
                                       if (next == todo.size()) fc.stop();
                                       return next++;
                                     }) &
          tbb::make_filter<size_t, std::shared_ptr<Loaded>>(
              tbb::filter_mode::parallel,
              [&](size_t t) {
                auto out = std::make_shared<Loaded>();
                out->status = load(t, out->tile);
                return out;
              }) &
          tbb::make_filter<std::shared_ptr<Loaded>, void>(
              tbb::filter_mode::serial_in_order, [&](std::shared_ptr<Loaded> loaded) {
                if (!failed.ok()) return;
                if (!loaded->status.ok()) {
                  failed = loaded->status;
                  return;
                }
                assembler.Add(std::move(loaded->tile));
              }));
  if (!failed.ok()) return failed;
  return assembler.Finish();
}

/// INVALID_ARGUMENT unless `snapshot`'s lattice has the project's vossel size (a commit's or a
/// put's input).
absl::Status SameVosselSize(const Snapshot& snapshot, const ProjectSettings& settings) {
  if (std::fabs(snapshot.geometry.vossel_size_m - settings.vossel_size_m) >
      1e-9 * settings.vossel_size_m) {
    return absl::InvalidArgumentError(
        absl::StrCat("snapshot vossel size ", snapshot.geometry.vossel_size_m,
                     " m differs from the project's ", settings.vossel_size_m, " m"));
  }
  return absl::OkStatus();
}

/// The objects of one tile as written by a commit.
struct WrittenTile {
  tiles::TileKey key;
  std::map<std::string, ManifestEntry> layers;  ///< empty: the tile has no vossels any more
  CommitTimes times;  ///< its steps' thread seconds (cut, encodings, puts)
};

using SteadyClock = std::chrono::steady_clock;

// Seconds from `t` to now, and `t` moved to now: a lap of a step timer.
double Lap(SteadyClock::time_point& t) {
  const SteadyClock::time_point now = SteadyClock::now();
  const double s = std::chrono::duration<double>(now - t).count();
  t = now;
  return s;
}

}  // namespace

absl::Status ValidateRequestId(const std::string& id) {
  bool ok = !id.empty() && id.size() <= 128;
  for (char c : id) ok = ok && (absl::ascii_isalnum(c) || c == '.' || c == '_' || c == ':' || c == '-');
  if (!ok) {
    return absl::InvalidArgumentError(absl::StrCat(
        "invalid request id \"", absl::CHexEscape(id.substr(0, 64)),
        id.size() > 64 ? "...\" (" : "\" (", id.size(),
        " bytes): use 1-128 characters of [A-Za-z0-9._:-], e.g. a UUID"));
  }
  return absl::OkStatus();
}

absl::Status ValidateProjectName(const std::string& name) {
  bool ok = !name.empty() && name.size() <= 63 && absl::ascii_isalnum(name[0]);
  for (char c : name) {
    ok = ok && ((c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '.' || c == '_' ||
                c == '-');
  }
  if (!ok) {
    // Echoed escaped and cut to 64 bytes: the name is the client's, and may be anything.
    return absl::InvalidArgumentError(absl::StrCat(
        "invalid project name \"", absl::CHexEscape(name.substr(0, 64)),
        name.size() > 64 ? "...\" (" : "\" (", name.size(),
        " bytes): use 1-63 characters of [a-z0-9._-], starting with a letter or digit"));
  }
  return absl::OkStatus();
}

struct ProjectStore::Impl {
  fs::path dir;
  std::string name;
  ProjectSettings settings;
  std::string created_utc;
  std::atomic<int64_t> head{0};

  mutable std::mutex db_mu;  ///< guards `db` (statements are short)
  Db db;
  std::mutex commit_mu;  ///< one commit at a time
  CommitTimes last_commit_times;  ///< under commit_mu
  std::unique_ptr<ObjectStore> objects;

  CommitStage fault_stage = CommitStage::kNone;
  bool fault_crash = false;

  std::optional<OperationRecord> operation;  ///< BeginOperation's, recorded by the next Commit
  std::optional<Eigen::Vector3d> proposed_origin;  ///< ProposeOrigin's, fixed by the next Commit
  mutable std::mutex origin_mu;                    ///< guards `origin`
  std::optional<Eigen::Vector3d> origin;           ///< x_0 once fixed (§1)

  explicit Impl(Db d) : db(std::move(d)) {}

  /// Brings the catalog back to HEAD (drops rows newer than HEAD), removes staging files, then
  /// collects objects and blobs no kept version references.
  absl::Status RecoverToHead(int64_t head_version) {
    {
      std::lock_guard<std::mutex> lock(db_mu);
      if (absl::Status s = internal::DropRowsNewerThan(db, head_version); !s.ok()) return s;
    }
    if (absl::Status s = objects->CleanStaging(); !s.ok()) return s;
    std::error_code ec;
    for (const fs::path& d : {dir / kBlobsDir, dir}) {
      for (const fs::directory_entry& e : fs::directory_iterator(d, ec)) {
        const std::string n = e.path().filename().string();
        if (absl::StartsWith(n, kTmpPrefix) || absl::StartsWith(n, ".HEAD.tmp-")) {
          if (absl::Status s = RemoveAll(e.path()); !s.ok()) return s;
        }
      }
    }
    return Collect().status();
  }

  /// Retention and garbage collection (see ProjectStore::CollectGarbage).
  absl::StatusOr<int64_t> Collect() {
    objects->Discard();  // puts no commit named (a stopped flow's) go with the garbage
    const int64_t h = head.load();
    const int64_t oldest_kept = h - std::max(0, settings.keep_versions);
    std::set<std::string> live_objects, live_blobs;
    {
      std::lock_guard<std::mutex> lock(db_mu);
      absl::Status s = db.Exec("BEGIN IMMEDIATE;");
      auto run = [&](std::string_view sql) {
        if (s.ok()) {
          s = RunSql(db, sql, [&](Stmt& st) { st.Bind(1, oldest_kept).Bind(2, h); });
        }
      };
      run("UPDATE versions SET pruned = 1 WHERE version < ?1 AND pinned = 0 AND version <> ?2");
      run("DELETE FROM manifest WHERE version IN (SELECT version FROM versions WHERE pruned = 1)");
      run("DELETE FROM reach WHERE version IN (SELECT version FROM versions WHERE pruned = 1)");
      if (s.ok()) s = db.Exec("COMMIT;");
      if (!s.ok()) {
        db.Exec("ROLLBACK;").IgnoreError();
        return s;
      }
      const std::pair<const char*, std::set<std::string>*> queries[] = {
          {"SELECT object FROM manifest UNION SELECT object FROM reach", &live_objects},
          {"SELECT DISTINCT b.blob_sha256 FROM (SELECT scan_id, blob_sha256 FROM sources UNION ALL "
           "SELECT scan_id, mask_sha256 FROM sources WHERE mask_sha256 != '' UNION ALL "
           "SELECT scan_id, blob_sha256 FROM visual_references) b JOIN scan_lives l "
           "ON b.scan_id = l.scan_id WHERE EXISTS (SELECT 1 FROM versions v WHERE v.pruned = 0 "
           "AND l.from_version <= v.version AND (l.to_version IS NULL OR l.to_version > v.version))",
           &live_blobs}};
      for (const auto& [sql, live_set] : queries) {
        absl::StatusOr<Stmt> st = db.Prepare(sql);
        if (!st.ok()) return st.status();
        std::set<std::string>& live = *live_set;
        for (;;) {
          absl::StatusOr<bool> row = st->Step();
          if (!row.ok()) return row.status();
          if (!*row) break;
          live.insert(st->Text(0));
        }
      }
    }
    int64_t removed = 0;
    absl::StatusOr<std::vector<std::string>> names = objects->List();
    if (!names.ok()) return names.status();
    for (const std::string& n : *names) {
      if (live_objects.count(n)) continue;
      if (absl::Status s = objects->Remove(n); !s.ok()) return s;
      ++removed;
    }
    std::error_code ec;
    for (const fs::directory_entry& e : fs::directory_iterator(dir / kBlobsDir, ec)) {
      const std::string n = e.path().filename().string();
      if (!IsSha256Hex(n) || live_blobs.count(n)) continue;
      // A blob newer than every scan row belongs to an ingest that has not committed yet (the
      // single writer calls this only from its own commit or from Open, so there is none).
      if (absl::Status s = RemoveAll(e.path()); !s.ok()) return s;
      ++removed;
    }
    if (absl::Status s = objects->Sync(); !s.ok()) return s;
    if (absl::Status s = internal::FsyncPath(dir / kBlobsDir); !s.ok()) return s;
    return removed;
  }

  /// Kept versions numbered first..last, oldest first (ListVersions, HeadInfo).
  absl::StatusOr<std::vector<VersionInfo>> QueryVersions(int64_t first, int64_t last);

  absl::StatusOr<bool> IsKept(int64_t version) {
    std::lock_guard<std::mutex> lock(db_mu);
    absl::StatusOr<Stmt> st = db.Prepare("SELECT pruned FROM versions WHERE version = ?1");
    if (!st.ok()) return st.status();
    st->Bind(1, version);
    absl::StatusOr<bool> row = st->Step();
    if (!row.ok()) return row.status();
    return *row && st->Int(0) == 0;
  }

  /// Writes the objects of the tiles `geometry_keys` (every layer) and `record_keys` (all but
  /// the geometry) cut from `snapshot`, in one parallel pass over them, the tiles with most
  /// work first (geometry, then by vossels) so that no thread is left with a large tile at the
  /// end; each tile is cut as it is written, so a commit holds only the tiles its threads are
  /// writing. The result lists the geometry tiles, then the record tiles, each in key order.
  absl::StatusOr<std::vector<WrittenTile>> WriteTiles(const Snapshot& snapshot,
                                                      const std::set<tiles::TileKey>& geometry_keys,
                                                      const std::set<tiles::TileKey>& record_keys) {
    const tiles::TileCutter cutter(snapshot.geometry, snapshot.records, snapshot.fused,
                                   settings.tile_vossels, &snapshot.profile_fused);
    std::vector<tiles::TileKey> ordered(geometry_keys.begin(), geometry_keys.end());
    ordered.insert(ordered.end(), record_keys.begin(), record_keys.end());
    const size_t with_geometry_count = geometry_keys.size();
    std::vector<size_t> by_work(ordered.size());
    std::iota(by_work.begin(), by_work.end(), size_t{0});
    std::stable_sort(by_work.begin(), by_work.end(), [&](size_t a, size_t b) {
      const bool ga = a < with_geometry_count, gb = b < with_geometry_count;
      if (ga != gb) return ga;
      return cutter.VosselsOf(ordered[a]) > cutter.VosselsOf(ordered[b]);
    });
    std::vector<WrittenTile> out(ordered.size());
    std::vector<absl::Status> status(ordered.size());
    std::atomic<size_t> next{0};
    const int threads = tbb::this_task_arena::max_concurrency();
    tbb::parallel_for(0, threads, [&](int) {
      for (size_t i = next++; i < by_work.size(); i = next++) {
        const size_t t = by_work[i];
        const bool with_geometry = t < with_geometry_count;
        SteadyClock::time_point clock = SteadyClock::now();
        CommitTimes& times = out[t].times;
        const tiles::TileContents tile = cutter.Cut(ordered[t]);
        times.cut_s += Lap(clock);
        out[t].key = tile.key;
        if (tile.geometry.size() == 0) continue;
        // Each layer's file is made in memory and put from there (hashed, written once).
        auto put = [&](const char* layer, const absl::StatusOr<std::string>& bytes,
                       double& encode_s) {
          encode_s += Lap(clock);
          if (!bytes.ok()) return bytes.status();
          absl::StatusOr<StoredObject> obj = objects->PutBytes(*bytes);
          times.put_s += Lap(clock);
          if (!obj.ok()) return obj.status();
          out[t].layers[layer] = {obj->sha256, int64_t(tile.geometry.size()),
                                  int64_t(tile.records.size()), obj->bytes};
          return absl::OkStatus();
        };
        absl::Status s;
        if (with_geometry) {
          s = put(kLayerGeometry, records::EncodeGeometry(tile.geometry), times.geometry_s);
        }
        if (s.ok()) {
          s = put(kLayerRecords, records::EncodeRecords(tile.geometry, tile.records),
                  times.records_s);
        }
        if (s.ok()) {
          s = put(kLayerFusedDefault, records::EncodeFused(tile.geometry, tile.fused),
                  times.fused_s);
        }
        for (const auto& [layer, fused] : tile.profile_fused) {
          if (!s.ok()) break;
          s = put(layer.c_str(), records::EncodeFused(tile.geometry, fused), times.fused_s);
        }
        status[t] = s;
      }
    });
    for (const absl::Status& s : status) {
      if (!s.ok()) return s;
    }
    return out;
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
  if (settings.origin_m && !settings.origin_m->allFinite()) {
    return absl::InvalidArgumentError("the project origin must be finite");
  }
  const int T = settings.tile_vossels;
  if (T < 8 || T > 512 || (T & (T - 1)) != 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        "tile_vossels must be a power of two from 8 to 512; got ", T));
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
  if (!ec) fs::create_directories(tmp / kObjectsDir, ec);
  if (ec) return fail(internal::ErrnoError("cannot create", tmp, ec.value()));
  {
    absl::StatusOr<Db> db = Db::Open(tmp / kCatalogFile, /*create=*/true);
    if (!db.ok()) return fail(db.status());
    if (absl::Status s = internal::CreateSchema(*db); !s.ok()) return fail(s);
    absl::Status s = RunSql(*db,
        "INSERT INTO project(id, name, description, vossel_size_m, keep_versions, tile_vossels, "
        "created_utc, origin_fixed, origin_x, origin_y, origin_z) "
        "VALUES (1, ?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10)",
        [&](Stmt& st) {
          st.Bind(1, name).Bind(2, settings.description).Bind(3, settings.vossel_size_m);
          st.Bind(4, int64_t{settings.keep_versions}).Bind(5, int64_t{T});
          st.Bind(6, internal::UtcNowIso8601());
          const Eigen::Vector3d o = settings.origin_m.value_or(Eigen::Vector3d::Zero());
          st.Bind(7, int64_t{settings.origin_m.has_value()});
          st.Bind(8, o.x()).Bind(9, o.y()).Bind(10, o.z());
        });
    if (!s.ok()) return fail(s);
  }  // connection closed: the WAL is checkpointed before the rename
  for (absl::Status s : {internal::WriteFileDurable(tmp / kHeadFile, "0\n"),
                         internal::FsyncPath(tmp / kCatalogFile), internal::FsyncPath(tmp / kBlobsDir),
                         internal::FsyncPath(tmp / kObjectsDir), internal::FsyncPath(tmp)}) {
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
    int64_t schema = 0;
    {
      absl::StatusOr<Stmt> st = impl->db.Prepare("SELECT MAX(version) FROM schema_version");
      if (!st.ok()) return st.status();
      absl::StatusOr<bool> row = st->Step();
      if (!row.ok()) return row.status();
      schema = *row ? st->Int(0) : 0;
    }  // the statement is released before migrating
    if (schema >= 2 && schema < internal::kCatalogSchemaVersion) {
      if (absl::Status s = internal::MigrateSchema(impl->db, schema); !s.ok()) return s;
      schema = internal::kCatalogSchemaVersion;
    }
    if (schema != internal::kCatalogSchemaVersion) {
      return absl::FailedPreconditionError(absl::StrCat(
          "catalog ", (dir / kCatalogFile).string(), " has schema version ", schema,
          "; this build reads version ", internal::kCatalogSchemaVersion,
          (schema < internal::kCatalogSchemaVersion
               ? " (an untiled project of an earlier vasl: ingest its scans into a new project)"
               : ": upgrade vasl")));
    }
  }
  {
    absl::StatusOr<Stmt> st = impl->db.Prepare(
        "SELECT name, description, vossel_size_m, keep_versions, tile_vossels, created_utc, "
        "origin_fixed, origin_x, origin_y, origin_z FROM project WHERE id = 1");
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
    impl->settings.tile_vossels = static_cast<int>(st->Int(4));
    impl->created_utc = st->Text(5);
    if (st->Int(6) != 0) impl->origin = Eigen::Vector3d(st->Real(7), st->Real(8), st->Real(9));
  }
  absl::StatusOr<std::unique_ptr<ObjectStore>> objects = OpenLocalObjectStore(dir / kObjectsDir);
  if (!objects.ok()) return objects.status();
  impl->objects = std::move(*objects);
  // HEAD is the truth: anything newer is the debris of an interrupted commit.
  if (absl::Status s = impl->RecoverToHead(*head); !s.ok()) return s;
  return std::unique_ptr<ProjectStore>(new ProjectStore(std::move(impl)));
}

const std::string& ProjectStore::name() const { return impl_->name; }
const ProjectSettings& ProjectStore::settings() const { return impl_->settings; }
const std::string& ProjectStore::created_utc() const { return impl_->created_utc; }

std::optional<Eigen::Vector3d> ProjectStore::origin() const {
  std::lock_guard<std::mutex> lock(impl_->origin_mu);
  return impl_->origin;
}
const fs::path& ProjectStore::dir() const { return impl_->dir; }
int64_t ProjectStore::head_version() const { return impl_->head.load(); }
const ObjectStore& ProjectStore::objects() const { return *impl_->objects; }
ObjectStore& ProjectStore::writable_objects() { return *impl_->objects; }

absl::StatusOr<VersionInfo> ProjectStore::HeadInfo() const {
  const int64_t head = impl_->head.load();
  if (head == 0) return VersionInfo{};
  absl::StatusOr<std::vector<VersionInfo>> one = impl_->QueryVersions(head, head);
  if (!one.ok()) return one.status();
  if (one->empty()) {
    return absl::DataLossError(absl::StrCat("catalog has no row for HEAD version ", head,
                                            " of project ", impl_->name));
  }
  return one->front();
}

absl::StatusOr<std::vector<VersionInfo>> ProjectStore::ListVersions() const {
  return impl_->QueryVersions(1, impl_->head.load());
}

absl::StatusOr<std::vector<VersionInfo>> ProjectStore::Impl::QueryVersions(int64_t first,
                                                                          int64_t last) {
  std::lock_guard<std::mutex> lock(db_mu);
  absl::StatusOr<Stmt> st = db.Prepare(
      "SELECT v.version, v.vossel_count, v.record_count, v.created_utc, v.made_by, "
      "v.bytes_written, v.pinned, "
      "(SELECT COUNT(*) FROM manifest m WHERE m.version = v.version AND m.layer = 'geometry'), "
      "(SELECT COALESCE(SUM(bytes), 0) FROM manifest m WHERE m.version = v.version) + "
      "(SELECT COALESCE(SUM(bytes), 0) FROM reach r WHERE r.version = v.version) "
      "FROM versions v WHERE v.pruned = 0 AND v.version BETWEEN ?1 AND ?2 ORDER BY v.version");
  if (!st.ok()) return st.status();
  st->Bind(1, first).Bind(2, last);
  std::vector<VersionInfo> out;
  for (;;) {
    absl::StatusOr<bool> row = st->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    VersionInfo v;
    v.version = st->Int(0);
    v.vossel_count = st->Int(1);
    v.record_count = st->Int(2);
    v.created_utc = st->Text(3);
    v.made_by = st->Text(4);
    v.bytes_written = st->Int(5);
    v.pinned = st->Int(6) != 0;
    v.tile_count = st->Int(7);
    v.bytes_total = st->Int(8);
    out.push_back(std::move(v));
  }
  return out;
}

absl::Status ProjectStore::SetPinned(int64_t version, bool pinned) {
  absl::StatusOr<bool> kept = impl_->IsKept(version);
  if (!kept.ok()) return kept.status();
  if (!*kept || version > impl_->head.load()) {
    return absl::NotFoundError(absl::StrCat("project ", impl_->name, " has no kept version ",
                                            version));
  }
  std::lock_guard<std::mutex> lock(impl_->db_mu);
  return RunSql(impl_->db, "UPDATE versions SET pinned = ?2 WHERE version = ?1", [&](Stmt& st) {
    st.Bind(1, version).Bind(2, int64_t{pinned ? 1 : 0});
  });
}

absl::StatusOr<int64_t> ProjectStore::CollectGarbage() {
  std::lock_guard<std::mutex> commit_lock(impl_->commit_mu);
  return impl_->Collect();
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

absl::StatusOr<std::vector<ScanInfo>> ProjectStore::ListScans(int64_t version) const {
  const int64_t v = version == 0 ? impl_->head.load() : version;
  std::lock_guard<std::mutex> lock(impl_->db_mu);
  std::vector<ScanInfo> scans;
  std::map<int64_t, size_t> by_id;
  {
    absl::StatusOr<Stmt> st = impl_->db.Prepare(
        "SELECT s.id, s.name, s.rig, s.captured_utc, s.qx, s.qy, s.qz, s.qw, s.ox_m, s.oy_m, "
        "s.oz_m, s.batch, s.version, s.created_utc, COALESCE(l.to_version, 0) FROM scans s "
        "JOIN scan_lives l ON l.scan_id = s.id WHERE l.from_version <= ?1 "
        "AND (l.to_version IS NULL OR l.to_version > ?1) ORDER BY s.id");
    if (!st.ok()) return st.status();
    st->Bind(1, v);
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
      s.deleted_in = st->Int(14);
      by_id[s.id] = scans.size();
      scans.push_back(std::move(s));
    }
  }
  absl::StatusOr<Stmt> st = impl_->db.Prepare(
      "SELECT s.id, s.scan_id, s.name, s.modality, s.qx, s.qy, s.qz, s.qw, s.ox_m, s.oy_m, "
      "s.oz_m, s.blob_sha256, s.width_px, s.height_px, s.divergence_rad, s.point_count, s.camera, "
      "c.lidar_source, c.verdict, c.points_in_view, c.features, c.matched, c.cell_px, "
      "c.pixel_mean_px, c.pixel_p95_px, c.offset_mean_m, c.offset_p95_m, c.roundtrip_mean_m, "
      "c.roundtrip_p95_m, c.rotation_deg, c.note, s.mask_sha256 FROM sources s "
      "LEFT JOIN calibration c ON c.camera_source = s.id WHERE s.version <= ?1 ORDER BY s.id");
  if (!st.ok()) return st.status();
  st->Bind(1, v);
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
    src.camera = st->Text(16);
    src.mask_sha256 = st->Text(31);
    if (!st->IsNull(17)) {
      records::CalibrationHealth c;
      c.lidar_source = static_cast<int32_t>(st->Int(17));
      c.verdict = static_cast<records::CalibrationHealth::Verdict>(st->Int(18));
      c.points_in_view = st->Int(19);
      c.features = st->Int(20);
      c.matched = st->Int(21);
      c.cell_px = st->Real(22);
      c.pixel_mean_px = st->Real(23);
      c.pixel_p95_px = st->Real(24);
      c.offset_mean_m = st->Real(25);
      c.offset_p95_m = st->Real(26);
      c.roundtrip_mean_m = st->Real(27);
      c.roundtrip_p95_m = st->Real(28);
      c.rotation_deg = st->Real(29);
      c.note = st->Text(30);
      src.calibration = std::move(c);
    }
    auto it = by_id.find(src.scan_id);
    if (it != by_id.end()) scans[it->second].sources.push_back(std::move(src));
  }
  absl::StatusOr<Stmt> refs = impl_->db.Prepare(
      "SELECT scan_id, name, qx, qy, qz, qw, ox_m, oy_m, oz_m, blob_sha256, width_px, height_px, "
      "size_bytes FROM visual_references WHERE version <= ?1 ORDER BY scan_id, name");
  if (!refs.ok()) return refs.status();
  refs->Bind(1, v);
  for (;;) {
    absl::StatusOr<bool> row = refs->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    auto it = by_id.find(refs->Int(0));
    if (it == by_id.end()) continue;
    VisualReferenceInfo ref;
    ref.name = refs->Text(1);
    ref.pose = ColumnPose(*refs, 2);
    ref.blob_sha256 = refs->Text(9);
    ref.width_px = static_cast<int>(refs->Int(10));
    ref.height_px = static_cast<int>(refs->Int(11));
    ref.size_bytes = refs->Int(12);
    scans[it->second].visual_references.push_back(std::move(ref));
  }
  return scans;
}

absl::StatusOr<bool> ProjectStore::HasScan(const std::string& name) const {
  std::lock_guard<std::mutex> lock(impl_->db_mu);
  absl::StatusOr<Stmt> st =
      impl_->db.Prepare("SELECT 1 FROM scans s JOIN scan_lives l ON l.scan_id = s.id "
                        "WHERE s.name = ?1 AND l.to_version IS NULL");
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

absl::StatusOr<std::set<tiles::TileKey>> ProjectStore::SourceTiles(int32_t source_id) const {
  std::lock_guard<std::mutex> lock(impl_->db_mu);
  absl::StatusOr<Stmt> st = impl_->db.Prepare(
      "SELECT tx, ty, tz FROM source_tiles WHERE source_id = ?1 AND version <= ?2");
  if (!st.ok()) return st.status();
  st->Bind(1, int64_t{source_id}).Bind(2, impl_->head.load());
  std::set<tiles::TileKey> out;
  for (;;) {
    absl::StatusOr<bool> row = st->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    out.insert({int32_t(st->Int(0)), int32_t(st->Int(1)), int32_t(st->Int(2))});
  }
  return out;
}

absl::StatusOr<Manifest> ProjectStore::LoadManifest(int64_t version) const {
  const int64_t head = impl_->head.load();
  absl::StatusOr<bool> kept = impl_->IsKept(version);
  if (!kept.ok()) return kept.status();
  if (version <= 0 || version > head || !*kept) {
    return absl::NotFoundError(absl::StrCat(
        "project ", impl_->name, " has no version ", version, " (HEAD is ", head,
        "; retention keeps the last ", impl_->settings.keep_versions, " before HEAD and pinned ones)"));
  }
  Manifest m;
  std::lock_guard<std::mutex> lock(impl_->db_mu);
  absl::StatusOr<Stmt> st = impl_->db.Prepare(
      "SELECT tx, ty, tz, layer, object, vossels, records, bytes FROM manifest WHERE version = ?1");
  if (!st.ok()) return st.status();
  st->Bind(1, version);
  for (;;) {
    absl::StatusOr<bool> row = st->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    const tiles::TileKey key{int32_t(st->Int(0)), int32_t(st->Int(1)), int32_t(st->Int(2))};
    m.tiles[key][st->Text(3)] = {st->Text(4), st->Int(5), st->Int(6), st->Int(7)};
  }
  absl::StatusOr<Stmt> rs =
      impl_->db.Prepare("SELECT source_id, object, bytes FROM reach WHERE version = ?1");
  if (!rs.ok()) return rs.status();
  rs->Bind(1, version);
  for (;;) {
    absl::StatusOr<bool> row = rs->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    m.reach[int32_t(rs->Int(0))] = {rs->Text(1), 0, 0, rs->Int(2)};
  }
  return m;
}

std::string FusedLayerName(const std::string& name, int32_t revision) {
  if (name == "default") return kLayerFusedDefault;
  return absl::StrCat("fused-", name, "@", revision);
}

bool ParseFusedLayerName(const std::string& layer, std::string* name, int32_t* revision) {
  constexpr std::string_view kPrefix = "fused-";
  if (layer.rfind(kPrefix, 0) != 0 || layer == kLayerFusedDefault) return false;
  const size_t at = layer.rfind('@');
  if (at == std::string::npos || at <= kPrefix.size()) return false;
  int32_t r = 0;
  if (!absl::SimpleAtoi(absl::string_view(layer.data() + at + 1, layer.size() - at - 1), &r) ||
      r < 1) {
    return false;
  }
  *name = layer.substr(kPrefix.size(), at - kPrefix.size());
  *revision = r;
  return true;
}

std::vector<std::string> CompleteProfileLayers(const Manifest& manifest) {
  std::map<std::string, size_t> count;
  for (const auto& [key, layers] : manifest.tiles) {
    for (const auto& [layer, entry] : layers) {
      std::string name;
      int32_t revision = 0;
      if (ParseFusedLayerName(layer, &name, &revision)) ++count[layer];
    }
  }
  std::vector<std::string> out;
  for (const auto& [layer, n] : count) {
    if (n == manifest.tiles.size()) out.push_back(layer);
  }
  return out;
}

absl::StatusOr<StoredProfile> ProjectStore::PutProfile(
    const std::string& name, const std::function<std::string(int32_t)>& text_of) {
  Impl& im = *impl_;
  std::lock_guard<std::mutex> lock(im.db_mu);
  absl::Status s = im.db.Exec("BEGIN IMMEDIATE;");
  if (!s.ok()) return s;
  StoredProfile out;
  out.name = name;
  out.created_utc = internal::UtcNowIso8601();
  {
    absl::StatusOr<Stmt> st =
        im.db.Prepare("SELECT COALESCE(MAX(revision), 0) FROM profiles WHERE name = ?1");
    absl::StatusOr<bool> row = st.ok() ? st->Bind(1, name).Step() : st.status();
    if (!row.ok()) s = row.status();
    else out.revision = int32_t(st->Int(0)) + 1;
  }
  if (s.ok()) {
    out.text = text_of(out.revision);
    s = RunSql(im.db, "INSERT INTO profiles(name, revision, body, created_utc) VALUES (?1, ?2, ?3, ?4)",
               [&](Stmt& st) {
                 st.Bind(1, name).Bind(2, int64_t{out.revision}).Bind(3, out.text);
                 st.Bind(4, out.created_utc);
               });
  }
  if (s.ok()) s = im.db.Exec("COMMIT;");
  if (!s.ok()) {
    im.db.Exec("ROLLBACK;").IgnoreError();
    return s;
  }
  return out;
}

absl::StatusOr<StoredProfile> ProjectStore::GetProfile(const std::string& name,
                                                       int32_t revision) const {
  std::lock_guard<std::mutex> lock(impl_->db_mu);
  absl::StatusOr<Stmt> st = impl_->db.Prepare(
      revision > 0 ? "SELECT revision, body, created_utc FROM profiles WHERE name = ?1 AND revision = ?2"
                   : "SELECT revision, body, created_utc FROM profiles WHERE name = ?1 "
                     "ORDER BY revision DESC LIMIT 1");
  if (!st.ok()) return st.status();
  st->Bind(1, name);
  if (revision > 0) st->Bind(2, int64_t{revision});
  absl::StatusOr<bool> row = st->Step();
  if (!row.ok()) return row.status();
  if (!*row) {
    return absl::NotFoundError(absl::StrCat(
        "project ", impl_->name, " has no weighting profile \"", name, "\"",
        revision > 0 ? absl::StrCat(" at revision ", revision) : ""));
  }
  return StoredProfile{name, int32_t(st->Int(0)), st->Text(1), st->Text(2)};
}

absl::StatusOr<std::vector<StoredProfile>> ProjectStore::ListProfiles() const {
  std::lock_guard<std::mutex> lock(impl_->db_mu);
  absl::StatusOr<Stmt> st = impl_->db.Prepare(
      "SELECT p.name, p.revision, p.body, p.created_utc FROM profiles p "
      "WHERE p.revision = (SELECT MAX(q.revision) FROM profiles q WHERE q.name = p.name) "
      "ORDER BY p.name");
  if (!st.ok()) return st.status();
  std::vector<StoredProfile> out;
  for (;;) {
    absl::StatusOr<bool> row = st->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    out.push_back({st->Text(0), int32_t(st->Int(1)), st->Text(2), st->Text(3)});
  }
  return out;
}

absl::StatusOr<StoredLensMap> ProjectStore::PutLensMap(const std::string& rig,
                                                       const std::string& camera,
                                                       const std::string& text) {
  std::lock_guard<std::mutex> lock(impl_->db_mu);
  StoredLensMap out{0, rig, camera, text, internal::UtcNowIso8601()};
  absl::Status s = RunSql(
      impl_->db, "INSERT INTO lens_maps(rig, camera, body, created_utc) VALUES (?1, ?2, ?3, ?4)",
      [&](Stmt& st) { st.Bind(1, rig).Bind(2, camera).Bind(3, text).Bind(4, out.created_utc); });
  if (!s.ok()) return s;
  out.id = impl_->db.LastInsertRowId();
  return out;
}

absl::StatusOr<StoredLensMap> ProjectStore::GetLensMap(int64_t id) const {
  std::lock_guard<std::mutex> lock(impl_->db_mu);
  absl::StatusOr<Stmt> st = impl_->db.Prepare(
      "SELECT rig, camera, body, created_utc FROM lens_maps WHERE id = ?1");
  if (!st.ok()) return st.status();
  st->Bind(1, id);
  absl::StatusOr<bool> row = st->Step();
  if (!row.ok()) return row.status();
  if (!*row) {
    return absl::NotFoundError(
        absl::StrCat("project ", impl_->name, " has no lens map ", id));
  }
  return StoredLensMap{id, st->Text(0), st->Text(1), st->Text(2), st->Text(3)};
}

absl::StatusOr<std::vector<StoredLensMap>> ProjectStore::ListLensMaps() const {
  std::lock_guard<std::mutex> lock(impl_->db_mu);
  absl::StatusOr<Stmt> st = impl_->db.Prepare(
      "SELECT id, rig, camera, body, created_utc FROM lens_maps ORDER BY id");
  if (!st.ok()) return st.status();
  std::vector<StoredLensMap> out;
  for (;;) {
    absl::StatusOr<bool> row = st->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    out.push_back({st->Int(0), st->Text(1), st->Text(2), st->Text(3), st->Text(4)});
  }
  return out;
}

absl::StatusOr<int64_t> ProjectStore::RecordRender(const RenderRecord& r) {
  std::lock_guard<std::mutex> lock(impl_->db_mu);
  absl::Status s = RunSql(
      impl_->db,
      "INSERT INTO renders(version, profile, revision, projection, width_px, height_px, qx, qy, "
      "qz, qw, ox_m, oy_m, oz_m, camera, created_utc) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, "
      "?9, ?10, ?11, ?12, ?13, ?14, ?15)",
      [&](Stmt& st) {
        st.Bind(1, r.version).Bind(2, r.profile).Bind(3, int64_t{r.revision}).Bind(4, r.projection);
        st.Bind(5, int64_t{r.width_px}).Bind(6, int64_t{r.height_px});
        BindPose(st, 7, r.pose);
        st.Bind(14, r.camera).Bind(15, internal::UtcNowIso8601());
      });
  if (!s.ok()) return s;
  return impl_->db.LastInsertRowId();
}

absl::StatusOr<RenderRecord> ProjectStore::GetRender(int64_t id) const {
  std::lock_guard<std::mutex> lock(impl_->db_mu);
  absl::StatusOr<Stmt> st = impl_->db.Prepare(
      "SELECT version, profile, revision, projection, width_px, height_px, qx, qy, qz, qw, ox_m, "
      "oy_m, oz_m, camera, created_utc FROM renders WHERE id = ?1");
  if (!st.ok()) return st.status();
  st->Bind(1, id);
  absl::StatusOr<bool> row = st->Step();
  if (!row.ok()) return row.status();
  if (!*row) {
    return absl::NotFoundError(absl::StrCat("project ", impl_->name, " has no render ", id));
  }
  RenderRecord r;
  r.id = id;
  r.version = st->Int(0);
  r.profile = st->Text(1);
  r.revision = int32_t(st->Int(2));
  r.projection = st->Text(3);
  r.width_px = int(st->Int(4));
  r.height_px = int(st->Int(5));
  r.pose = ColumnPose(*st, 6);
  r.camera = st->Text(13);
  r.created_utc = st->Text(14);
  return r;
}

absl::StatusOr<std::string> ProjectStore::ActiveProfile() const {
  std::lock_guard<std::mutex> lock(impl_->db_mu);
  absl::StatusOr<Stmt> st = impl_->db.Prepare("SELECT active_profile FROM project WHERE id = 1");
  if (!st.ok()) return st.status();
  absl::StatusOr<bool> row = st->Step();
  if (!row.ok()) return row.status();
  return *row ? st->Text(0) : std::string("default");
}

absl::Status ProjectStore::SetActiveProfile(const std::string& name) {
  if (name != "default") {
    absl::StatusOr<StoredProfile> p = GetProfile(name);
    if (!p.ok()) return p.status();
  }
  std::lock_guard<std::mutex> lock(impl_->db_mu);
  return RunSql(impl_->db, "UPDATE project SET active_profile = ?1 WHERE id = 1",
                [&](Stmt& st) { st.Bind(1, name); });
}

absl::StatusOr<std::shared_ptr<const Snapshot>> ProjectStore::LoadSnapshot(
    int64_t version, const std::vector<std::string>& profile_layers, bool with_records,
    const std::set<tiles::TileKey>* only_tiles) const {
  if (version < 0) {
    return absl::InvalidArgumentError(absl::StrCat("version must be >= 0; got ", version));
  }
  auto snap = std::make_shared<Snapshot>();
  snap->version = version;
  snap->tile_vossels = impl_->settings.tile_vossels;
  snap->fused.profile = "default";
  snap->geometry.vossel_size_m = impl_->settings.vossel_size_m;
  if (version == 0) {
    records::CanonicalizeVosselOrder(snap->geometry);  // an empty index grid
    return std::shared_ptr<const Snapshot>(std::move(snap));
  }
  absl::StatusOr<Manifest> manifest = LoadManifest(version);
  if (!manifest.ok()) return manifest.status();
  snap->manifest = std::move(*manifest);
  snap->partial = only_tiles != nullptr;
  snap->records_loaded = with_records;
  absl::StatusOr<tiles::Assembled> read =
      ReadTiles(*impl_->objects, impl_->settings.vossel_size_m, version, snap->manifest,
                only_tiles, profile_layers, with_records);
  if (!read.ok()) return read.status();
  tiles::Assembled& all = *read;
  const ObjectStore& objects = *impl_->objects;
  snap->geometry = std::move(all.geometry);
  snap->records = std::move(all.records);
  snap->fused = std::move(all.fused);
  snap->profile_fused = std::move(all.profile_fused);
  if (snap->fused.profile.empty()) snap->fused.profile = "default";
  for (const auto& [source, entry] : snap->manifest.reach) {
    if (snap->partial) break;  // a partial snapshot's reader renders or queries: no revisits
    const std::string& object = entry.object;
    absl::StatusOr<std::string> bytes = objects.ReadBytes(object);
    if (!bytes.ok()) return bytes.status();
    absl::StatusOr<tiles::ReachRaster> reach = tiles::ParseReach(*bytes);
    if (!reach.ok()) {
      return absl::DataLossError(absl::StrCat("reach object ", object, ": ", reach.status().message()));
    }
    snap->reach[source] = std::move(*reach);
  }
  return std::shared_ptr<const Snapshot>(std::move(snap));
}

absl::StatusOr<records::RecordSet> ProjectStore::LoadRecords(
    int64_t version, const std::set<tiles::TileKey>& tiles,
    const records::VosselGeometry& geometry) const {
  if (!geometry.index_grid) return absl::InternalError("LoadRecords: geometry without index grid");
  absl::StatusOr<Manifest> manifest = LoadManifest(version);
  if (!manifest.ok()) return manifest.status();
  absl::StatusOr<tiles::Assembled> part =
      ReadTiles(*impl_->objects, impl_->settings.vossel_size_m, version, *manifest, &tiles, {},
                /*with_records=*/true);
  if (!part.ok()) return part.status();
  records::RecordSet out = std::move(part->records);
  const records::VosselGeometry& g = part->geometry;
  auto acc = geometry.index_grid->getConstAccessor();
  std::vector<int32_t> whole(g.size(), -1);
  for (size_t v = 0; v < g.size(); ++v) {
    int32_t k = -1;
    if (!acc.probeValue(g.coord[v], k)) {
      return absl::DataLossError(absl::StrCat(
          "version ", version, ": a vossel of tile ",
          tiles::ToString(tiles::TileOf(g.coord[v], impl_->settings.tile_vossels)),
          " is not in its geometry"));
    }
    whole[v] = k;
  }
  for (int32_t& v : out.vossel) v = whole[size_t(v)];
  out.SortByVossel();
  return out;
}

absl::StatusOr<std::set<tiles::TileKey>> ProjectStore::TilesWithRecordsOf(
    int64_t version, const std::set<int32_t>& sources) const {
  absl::StatusOr<Manifest> manifest = LoadManifest(version);
  if (!manifest.ok()) return manifest.status();
  const std::vector<tiles::TileKey> keys = [&] {
    std::vector<tiles::TileKey> k;
    for (const auto& [key, layers] : manifest->tiles) k.push_back(key);
    return k;
  }();
  std::vector<uint8_t> holds(keys.size(), 0);
  std::vector<absl::Status> status(keys.size());
  tbb::parallel_for(tbb::blocked_range<size_t>(0, keys.size(), 1),
                    [&](const tbb::blocked_range<size_t>& r) {
    for (size_t t = r.begin(); t != r.end(); ++t) {
      const std::set<tiles::TileKey> one = {keys[t]};
      absl::StatusOr<tiles::Assembled> tile =
          ReadTiles(*impl_->objects, impl_->settings.vossel_size_m, version, *manifest, &one,
                    {}, /*with_records=*/true);
      if (!tile.ok()) {
        status[t] = tile.status();
        continue;
      }
      for (int32_t s : tile->records.scan) {
        if (sources.count(s)) {
          holds[t] = 1;
          break;
        }
      }
    }
  });
  std::set<tiles::TileKey> out;
  for (size_t t = 0; t < keys.size(); ++t) {
    if (!status[t].ok()) return status[t];
    if (holds[t]) out.insert(keys[t]);
  }
  return out;
}

absl::StatusOr<std::map<tiles::TileKey, std::map<std::string, ManifestEntry>>>
ProjectStore::PutTiles(const Snapshot& snapshot, const std::set<tiles::TileKey>& tiles) {
  if (absl::Status s = SameVosselSize(snapshot, impl_->settings); !s.ok()) return s;
  absl::StatusOr<std::vector<WrittenTile>> written =
      impl_->WriteTiles(snapshot, tiles, /*record_keys=*/{});
  if (!written.ok()) return written.status();
  std::map<tiles::TileKey, std::map<std::string, ManifestEntry>> out;
  for (WrittenTile& w : *written) {
    if (!w.layers.empty()) out[w.key] = std::move(w.layers);
  }
  return out;
}

absl::StatusOr<int64_t> ProjectStore::Commit(const Snapshot& snapshot, const CommitPlan& plan) {
  Impl& im = *impl_;
  std::lock_guard<std::mutex> commit_lock(im.commit_mu);
  const CommitStage fault = std::exchange(im.fault_stage, CommitStage::kNone);
  const bool crash = im.fault_crash;
  auto injected_error = [](const char* where) {
    return absl::InternalError(absl::StrCat("injected commit failure after ", where));
  };

  // A change that adds the first scan fixes the origin proposed for it (ProposeOrigin).
  const bool fixes_origin = im.proposed_origin && plan.add_scan && !origin().has_value();
  // Bad input never changes the project: validate everything before writing.
  const bool no_snapshot = plan.layers_only || plan.rollback_to > 0;
  if (plan.rollback_to > 0) {
    if (plan.layers_only || !plan.put_layers.empty() || plan.add_scan || !plan.delete_scan.empty() ||
        plan.replace_all || !plan.geometry_tiles.empty() || !plan.record_tiles.empty() ||
        !plan.reach_sources.empty() || !plan.drop_reach.empty()) {
      return absl::InvalidArgumentError("a rollback commit changes nothing else");
    }
    if (plan.rollback_to >= im.head.load()) {
      return absl::InvalidArgumentError(absl::StrCat(
          "roll back to a version before HEAD (", im.head.load(), "); got ", plan.rollback_to));
    }
    absl::StatusOr<bool> kept = im.IsKept(plan.rollback_to);
    if (!kept.ok()) return kept.status();
    if (!*kept) {
      return absl::NotFoundError(absl::StrCat("project ", im.name, " no longer keeps version ",
                                              plan.rollback_to, " (retention removed it; pin "
                                              "versions you may roll back to)"));
    }
  }
  if (plan.layers_only &&
      (plan.add_scan || !plan.delete_scan.empty() || plan.replace_all ||
       !plan.geometry_tiles.empty() || !plan.record_tiles.empty() || !plan.reach_sources.empty() ||
       !plan.drop_reach.empty() || im.head.load() == 0)) {
    return absl::InvalidArgumentError(
        "a layers-only commit changes layers of an existing version and nothing else");
  }
  if (!plan.put_tiles.empty() && (!plan.replace_all || !plan.geometry_tiles.empty() ||
                                  !plan.record_tiles.empty() || !plan.put_layers.empty())) {
    return absl::InvalidArgumentError(
        "tiles put beforehand make a whole new version (replace_all) and nothing else");
  }
  if (snapshot.records_partial && plan.put_tiles.empty() && (plan.replace_all || no_snapshot)) {
    return absl::InvalidArgumentError(
        "a snapshot holding some tiles' records can commit only those tiles");
  }
  if (!no_snapshot) {
    if (absl::Status s = SameVosselSize(snapshot, im.settings); !s.ok()) return s;
  }
  if (plan.add_scan) {
    const ScanInfo& scan = *plan.add_scan;
    if (scan.name.empty()) return absl::InvalidArgumentError("scan name must not be empty");
    absl::StatusOr<bool> exists = HasScan(scan.name);
    if (!exists.ok()) return exists.status();
    if (*exists) {
      return absl::AlreadyExistsError(absl::StrCat("scan \"", scan.name,
                                                   "\" already exists in project ", im.name));
    }
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
  if (!plan.delete_scan.empty()) {
    absl::StatusOr<bool> exists = HasScan(plan.delete_scan);
    if (!exists.ok()) return exists.status();
    if (!*exists) {
      return absl::NotFoundError(absl::StrCat("project ", im.name, " has no scan \"",
                                              plan.delete_scan, "\""));
    }
  }
  const int64_t head = im.head.load();
  const int64_t version = head + 1;
  Manifest manifest;
  if (head > 0 && !plan.replace_all) {
    absl::StatusOr<Manifest> previous = LoadManifest(plan.rollback_to > 0 ? plan.rollback_to : head);
    if (!previous.ok()) return previous.status();
    manifest = std::move(*previous);
  }

  // 1. Objects of the changed tiles and reach rasters, fsynced. Nothing refers to them until
  //    the catalog does, so a failure here leaves only garbage for the next collection.
  CommitTimes times;
  SteadyClock::time_point clock = SteadyClock::now();
  std::set<tiles::TileKey> geometry_tiles = plan.geometry_tiles, record_tiles = plan.record_tiles;
  int64_t bytes_written = 0;
  if (!plan.put_tiles.empty()) {
    manifest.tiles = plan.put_tiles;  // written by PutTiles
    for (const auto& [key, layers] : plan.put_tiles) {
      if (!layers.count(kLayerGeometry) || !layers.count(kLayerRecords)) {
        return absl::InternalError(absl::StrCat("commit: tile ", tiles::ToString(key),
                                                " was put without its geometry or records"));
      }
      for (const auto& [layer, entry] : layers) bytes_written += entry.bytes;
    }
  } else if (plan.replace_all) {
    const std::vector<tiles::TileKey> tile_of =
        tiles::TilesOfVossels(snapshot.geometry, im.settings.tile_vossels);
    geometry_tiles = std::set<tiles::TileKey>(tile_of.begin(), tile_of.end());
  }
  for (const tiles::TileKey& key : geometry_tiles) record_tiles.erase(key);
  {
    absl::StatusOr<std::vector<WrittenTile>> written =
        im.WriteTiles(snapshot, geometry_tiles, record_tiles);
    if (!written.ok()) return written.status();
    times.tiles_wall_s = Lap(clock);
    for (size_t i = 0; i < written->size(); ++i) {
      WrittenTile& w = (*written)[i];
      times.cut_s += w.times.cut_s;
      times.geometry_s += w.times.geometry_s;
      times.records_s += w.times.records_s;
      times.fused_s += w.times.fused_s;
      times.put_s += w.times.put_s;
      const bool with_geometry = i < geometry_tiles.size();
      if (w.layers.empty()) {
        manifest.tiles.erase(w.key);
        continue;
      }
      // A rewritten tile keeps no layer it did not rewrite but its geometry: a profile's
      // fused values the flow did not recompute would be stale.
      std::map<std::string, ManifestEntry>& row = manifest.tiles[w.key];
      for (auto it = row.begin(); it != row.end();) {
        if (it->first != kLayerGeometry && !w.layers.count(it->first)) it = row.erase(it);
        else ++it;
      }
      for (auto& [layer, entry] : w.layers) {
        bytes_written += entry.bytes;
        row[layer] = entry;
      }
      if (!with_geometry && !manifest.tiles[w.key].count(kLayerGeometry)) {
        return absl::InternalError(absl::StrCat("commit: tile ", tiles::ToString(w.key),
                                                " has new records but no geometry object"));
      }
      // Every layer's counts follow the tile's new contents (a rewrite always has records).
      const ManifestEntry& fresh = w.layers.at(kLayerRecords);
      for (auto& [layer, entry] : manifest.tiles[w.key]) {
        entry.vossels = fresh.vossels;
        entry.records = fresh.records;
      }
    }
  }
  clock = SteadyClock::now();
  std::set<int32_t> reach_sources = plan.reach_sources;
  if (plan.replace_all) {
    manifest.reach.clear();
    for (const auto& [source, raster] : snapshot.reach) reach_sources.insert(source);
  }
  for (int32_t source : reach_sources) {
    auto it = snapshot.reach.find(source);
    if (it == snapshot.reach.end()) {
      return absl::InternalError(absl::StrCat("commit: no reach raster for source ", source));
    }
    absl::StatusOr<StoredObject> obj = im.objects->PutBytes(tiles::SerializeReach(it->second));
    if (!obj.ok()) return obj.status();
    bytes_written += obj->bytes;
    manifest.reach[source] = {obj->sha256, 0, 0, obj->bytes};
  }
  for (int32_t source : plan.drop_reach) manifest.reach.erase(source);
  for (const auto& [key, layers] : plan.put_layers) {
    auto tile = manifest.tiles.find(key);
    if (tile == manifest.tiles.end()) {
      return absl::InternalError(absl::StrCat("commit: layers for tile ", tiles::ToString(key),
                                              ", which version ", head, " does not have"));
    }
    for (const auto& [layer, entry] : layers) {
      if (layer == kLayerGeometry || layer == kLayerRecords) {
        return absl::InternalError("commit: put_layers may not replace geometry or records");
      }
      ManifestEntry e = entry;
      e.vossels = RecordsOf(tile->second).vossels;
      e.records = RecordsOf(tile->second).records;
      bytes_written += e.bytes;
      tile->second[layer] = e;
    }
  }
  int64_t vossel_count = int64_t(snapshot.geometry.size());
  int64_t record_count = int64_t(snapshot.records.size());
  if (no_snapshot || snapshot.records_partial) {
    vossel_count = record_count = 0;
    for (const auto& [key, layers] : manifest.tiles) {
      vossel_count += RecordsOf(layers).vossels;
      record_count += RecordsOf(layers).records;
    }
  }
  times.reach_wall_s = Lap(clock);
  if (absl::Status s = im.objects->Sync(); !s.ok()) return s;
  times.sync_wall_s = Lap(clock);
  if (fault == CommitStage::kAfterObjects) {
    if (!crash) im.Collect().IgnoreError();
    return injected_error("objects");
  }

  // 2. Catalog rows, one transaction.
  {
    std::lock_guard<std::mutex> lock(im.db_mu);
    const std::string now = internal::UtcNowIso8601();
    absl::Status s = im.db.Exec("BEGIN IMMEDIATE;");
    auto run = [&](std::string_view sql, auto&& bind) {
      if (s.ok()) s = RunSql(im.db, sql, bind);
    };
    run("INSERT INTO versions(version, vossel_count, record_count, created_utc, made_by, "
        "bytes_written) VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
        [&](Stmt& st) {
          st.Bind(1, version).Bind(2, vossel_count);
          st.Bind(3, record_count).Bind(4, now).Bind(5, plan.made_by);
          st.Bind(6, bytes_written);
        });
    for (const auto& [key, layers] : manifest.tiles) {
      for (const auto& [layer, e] : layers) {
        run("INSERT INTO manifest(version, tx, ty, tz, layer, object, vossels, records, bytes) "
            "VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9)",
            [&](Stmt& st) {
              st.Bind(1, version).Bind(2, int64_t{key.x}).Bind(3, int64_t{key.y});
              st.Bind(4, int64_t{key.z}).Bind(5, layer).Bind(6, e.object).Bind(7, e.vossels);
              st.Bind(8, e.records).Bind(9, e.bytes);
            });
      }
    }
    for (const auto& [source, e] : manifest.reach) {
      run("INSERT INTO reach(version, source_id, object, bytes) VALUES (?1, ?2, ?3, ?4)",
          [&](Stmt& st) {
            st.Bind(1, version).Bind(2, int64_t{source}).Bind(3, e.object).Bind(4, e.bytes);
          });
    }
    if (plan.rollback_to > 0 && s.ok()) {
      // Scans live at HEAD but not at the target end; scans live at the target but not at
      // HEAD live again, from this version on.
      auto live_at = [&](int64_t v) -> absl::StatusOr<std::set<int64_t>> {
        absl::StatusOr<Stmt> st = im.db.Prepare(
            "SELECT scan_id FROM scan_lives WHERE from_version <= ?1 "
            "AND (to_version IS NULL OR to_version > ?1)");
        if (!st.ok()) return st.status();
        st->Bind(1, v);
        std::set<int64_t> ids;
        for (;;) {
          absl::StatusOr<bool> row = st->Step();
          if (!row.ok()) return row.status();
          if (!*row) break;
          ids.insert(st->Int(0));
        }
        return ids;
      };
      absl::StatusOr<std::set<int64_t>> live_now = live_at(head), then = live_at(plan.rollback_to);
      if (!live_now.ok()) s = live_now.status();
      else if (!then.ok()) s = then.status();
      if (s.ok()) {
        for (int64_t id : *live_now) {
          if (then->count(id)) continue;
          run("UPDATE scan_lives SET to_version = ?2 WHERE scan_id = ?1 AND to_version IS NULL",
              [&](Stmt& st) { st.Bind(1, id).Bind(2, version); });
          run("UPDATE scans SET deleted_in = ?2 WHERE id = ?1 AND deleted_in IS NULL",
              [&](Stmt& st) { st.Bind(1, id).Bind(2, version); });
        }
        for (int64_t id : *then) {
          if (live_now->count(id)) continue;
          run("INSERT INTO scan_lives(scan_id, from_version) VALUES (?1, ?2)",
              [&](Stmt& st) { st.Bind(1, id).Bind(2, version); });
        }
      }
    }
    if (!plan.delete_scan.empty()) {
      run("UPDATE scans SET deleted_in = ?2 WHERE name = ?1 AND deleted_in IS NULL",
          [&](Stmt& st) { st.Bind(1, plan.delete_scan).Bind(2, version); });
      run("UPDATE scan_lives SET to_version = ?2 WHERE to_version IS NULL AND scan_id IN "
          "(SELECT id FROM scans WHERE name = ?1)",
          [&](Stmt& st) { st.Bind(1, plan.delete_scan).Bind(2, version); });
    }
    int64_t added_scan_id = 0;
    if (plan.add_scan) {
      const ScanInfo& scan = *plan.add_scan;
      run("INSERT INTO scans(name, rig, captured_utc, qx, qy, qz, qw, ox_m, oy_m, oz_m, "
          "batch, version, created_utc) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, "
          "?11, ?12, ?13)",
          [&](Stmt& st) {
            st.Bind(1, scan.name).Bind(2, scan.rig).Bind(3, scan.captured_utc);
            BindPose(st, 4, scan.pose);
            st.Bind(11, int64_t{scan.batch}).Bind(12, version).Bind(13, now);
          });
      const int64_t scan_id = s.ok() ? im.db.LastInsertRowId() : 0;
      added_scan_id = scan_id;
      run("INSERT INTO scan_lives(scan_id, from_version) VALUES (?1, ?2)",
          [&](Stmt& st) { st.Bind(1, scan_id).Bind(2, version); });
      for (const SourceInfo& src : scan.sources) {
        run("INSERT INTO sources(id, scan_id, name, modality, qx, qy, qz, qw, ox_m, oy_m, "
            "oz_m, blob_sha256, width_px, height_px, divergence_rad, point_count, version, camera, "
            "mask_sha256) "
            "VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15, ?16, "
            "?17, ?18, ?19)",
            [&](Stmt& st) {
              st.Bind(1, int64_t{src.id}).Bind(2, scan_id).Bind(3, src.name);
              st.Bind(4, int64_t{static_cast<int>(src.modality)});
              BindPose(st, 5, src.pose);
              st.Bind(12, src.blob_sha256).Bind(13, int64_t{src.width_px});
              st.Bind(14, int64_t{src.height_px}).Bind(15, src.divergence_rad);
              st.Bind(16, src.point_count).Bind(17, version).Bind(18, src.camera);
              st.Bind(19, src.mask_sha256);
            });
        if (!src.calibration) continue;
        const records::CalibrationHealth& c = *src.calibration;
        run("INSERT INTO calibration(camera_source, lidar_source, version, verdict, "
            "points_in_view, features, matched, cell_px, pixel_mean_px, pixel_p95_px, "
            "offset_mean_m, offset_p95_m, roundtrip_mean_m, roundtrip_p95_m, rotation_deg, note) "
            "VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15, ?16)",
            [&](Stmt& st) {
              st.Bind(1, int64_t{src.id}).Bind(2, int64_t{c.lidar_source}).Bind(3, version);
              st.Bind(4, int64_t{static_cast<int>(c.verdict)}).Bind(5, c.points_in_view);
              st.Bind(6, c.features).Bind(7, c.matched).Bind(8, c.cell_px);
              st.Bind(9, c.pixel_mean_px).Bind(10, c.pixel_p95_px).Bind(11, c.offset_mean_m);
              st.Bind(12, c.offset_p95_m).Bind(13, c.roundtrip_mean_m);
              st.Bind(14, c.roundtrip_p95_m).Bind(15, c.rotation_deg).Bind(16, c.note);
            });
      }
      for (const VisualReferenceInfo& ref : scan.visual_references) {
        run("INSERT INTO visual_references(scan_id, name, qx, qy, qz, qw, ox_m, oy_m, oz_m, "
            "blob_sha256, width_px, height_px, size_bytes, version) "
            "VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14)",
            [&](Stmt& st) {
              st.Bind(1, scan_id).Bind(2, ref.name);
              BindPose(st, 3, ref.pose);
              st.Bind(10, ref.blob_sha256).Bind(11, int64_t{ref.width_px});
              st.Bind(12, int64_t{ref.height_px}).Bind(13, ref.size_bytes).Bind(14, version);
            });
      }
      for (const auto& [source, keys] : plan.source_tiles) {
        for (const tiles::TileKey& key : keys) {
          run("INSERT OR IGNORE INTO source_tiles(source_id, tx, ty, tz, version) "
              "VALUES (?1, ?2, ?3, ?4, ?5)",
              [&](Stmt& st) {
                st.Bind(1, int64_t{source}).Bind(2, int64_t{key.x}).Bind(3, int64_t{key.y});
                st.Bind(4, int64_t{key.z}).Bind(5, version);
              });
        }
      }
      run("INSERT OR IGNORE INTO batches(id, kind, scan_id, version, created_utc) "
          "VALUES (?1, 'ingest', ?2, ?3, ?4)",
          [&](Stmt& st) {
            st.Bind(1, int64_t{scan.batch}).Bind(2, scan_id).Bind(3, version).Bind(4, now);
          });
    }
    if (fixes_origin) {
      run("UPDATE project SET origin_fixed = 1, origin_x = ?1, origin_y = ?2, origin_z = ?3 "
          "WHERE id = 1 AND origin_fixed = 0",
          [&](Stmt& st) {
            st.Bind(1, im.proposed_origin->x()).Bind(2, im.proposed_origin->y());
            st.Bind(3, im.proposed_origin->z());
          });
    }
    if (im.operation) {
      const OperationRecord& op = *im.operation;
      run("INSERT INTO operations(request_id, kind, subject, version, scan_id, created_utc) "
          "VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
          [&](Stmt& st) {
            st.Bind(1, op.request_id).Bind(2, op.kind).Bind(3, op.subject).Bind(4, version);
            st.Bind(5, added_scan_id).Bind(6, now);
          });
    }
    if (s.ok()) s = im.db.Exec("COMMIT;");
    if (!s.ok()) {
      im.db.Exec("ROLLBACK;").IgnoreError();
      if (absl::IsAlreadyExists(s) && plan.add_scan) {
        s = absl::AlreadyExistsError(absl::StrCat("scan \"", plan.add_scan->name,
                                                  "\" or one of its source ids already exists "
                                                  "in project ", im.name, " (", s.message(), ")"));
      }
      return s;  // objects written above are garbage for the next collection
    }
  }
  auto undo_catalog = [&](absl::Status s) {
    {
      std::lock_guard<std::mutex> lock(im.db_mu);
      internal::DropRowsNewerThan(im.db, head).IgnoreError();
    }
    im.Collect().IgnoreError();
    return s;
  };
  times.catalog_wall_s = Lap(clock);
  if (fault == CommitStage::kAfterCatalog) {
    return crash ? injected_error("catalog") : undo_catalog(injected_error("catalog"));
  }

  // 3. HEAD, atomically: the commit point.
  if (absl::Status s = internal::ReplaceFileAtomically(im.dir / kHeadFile,
                                                       absl::StrCat(version, "\n"));
      !s.ok()) {
    // If the rename itself happened, HEAD names the new version: it is committed.
    absl::StatusOr<std::string> text = internal::ReadWholeFile(im.dir / kHeadFile);
    if (!text.ok() || ParseVersion(*text) != version) return undo_catalog(s);
  }
  im.head = version;
  if (fixes_origin) {
    std::lock_guard<std::mutex> lock(im.origin_mu);
    im.origin = im.proposed_origin;
  }
  times.head_wall_s = Lap(clock);
  im.Collect().IgnoreError();  // best effort: a failure leaves garbage for the next one
  times.collect_wall_s = Lap(clock);
  im.last_commit_times = times;
  return version;
}

CommitTimes ProjectStore::LastCommitTimes() const {
  std::lock_guard<std::mutex> lock(impl_->commit_mu);
  return impl_->last_commit_times;
}

absl::StatusOr<std::vector<records::AttributeInfo>> ProjectStore::InspectRecords(
    int64_t version) const {
  absl::StatusOr<Manifest> m = LoadManifest(version);
  if (!m.ok()) return m.status();
  for (const auto& [key, layers] : m->tiles) {
    auto it = layers.find(kLayerRecords);
    if (it == layers.end() || it->second.records == 0) continue;
    absl::StatusOr<fs::path> path = impl_->objects->LocalPath(it->second.object);
    if (!path.ok()) return path.status();
    return records::ListRecordAttributes(*path);
  }
  return absl::FailedPreconditionError(
      absl::StrCat("version ", version, " of project ", impl_->name, " holds no records"));
}

void ProjectStore::BeginOperation(const OperationRecord& op) {
  std::lock_guard<std::mutex> lock(impl_->commit_mu);
  impl_->operation = op;
}

void ProjectStore::EndOperation() {
  std::lock_guard<std::mutex> lock(impl_->commit_mu);
  impl_->operation.reset();
  impl_->proposed_origin.reset();
}

void ProjectStore::ProposeOrigin(const Eigen::Vector3d& origin_m) {
  std::lock_guard<std::mutex> lock(impl_->commit_mu);
  impl_->proposed_origin = origin_m;
}

absl::StatusOr<std::optional<OperationRecord>> ProjectStore::FindOperation(
    const std::string& request_id) const {
  std::lock_guard<std::mutex> lock(impl_->db_mu);
  absl::StatusOr<Stmt> st = impl_->db.Prepare(
      "SELECT kind, subject, version, scan_id, answer_hex, created_utc FROM operations "
      "WHERE request_id = ?1");
  if (!st.ok()) return st.status();
  st->Bind(1, request_id);
  absl::StatusOr<bool> row = st->Step();
  if (!row.ok()) return row.status();
  if (!*row) return std::optional<OperationRecord>();
  OperationRecord op;
  op.request_id = request_id;
  op.kind = st->Text(0);
  op.subject = st->Text(1);
  op.version = st->Int(2);
  op.scan_id = st->Int(3);
  op.answer = absl::HexStringToBytes(st->Text(4));
  op.created_utc = st->Text(5);
  return std::optional<OperationRecord>(std::move(op));
}

absl::Status ProjectStore::SetOperationAnswer(const std::string& request_id,
                                              const std::string& answer) {
  std::lock_guard<std::mutex> lock(impl_->db_mu);
  return RunSql(impl_->db, "UPDATE operations SET answer_hex = ?2 WHERE request_id = ?1",
                [&](Stmt& st) { st.Bind(1, request_id).Bind(2, absl::BytesToHexString(answer)); });
}

void ProjectStore::InjectCommitFailureForTesting(CommitStage stage, bool simulate_crash) {
  std::lock_guard<std::mutex> lock(impl_->commit_mu);
  impl_->fault_stage = stage;
  impl_->fault_crash = simulate_crash;
}

}  // namespace vasl::store

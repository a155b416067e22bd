// ARCHITECTURE.md "Storage of one project": layout, atomic commit, crash recovery, blobs,
// retention of the project store (project_store.h).
#include "lattice/store/project_store.h"

#include <sqlite3.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <random>
#include <set>
#include <string>
#include <thread>
#include <tuple>
#include <vector>

#include <gtest/gtest.h>
#include <tbb/task_arena.h>

#include "lattice/records/record_grid.h"
#include "lattice/tiles/tile_split.h"

namespace vasl::store {
namespace {

namespace fs = std::filesystem;
using records::Modality;

fs::path TestRoot(const std::string& name) {
  fs::path dir = fs::temp_directory_path() /
                 ("vasl-store-" + name + "-" + std::to_string(::getpid()));
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

geometry::Pose PoseAt(double x, double y, double z, double yaw_rad) {
  geometry::Pose p;
  p.q_world_sensor = Eigen::Quaterniond(Eigen::AngleAxisd(yaw_rad, Eigen::Vector3d::UnitZ()));
  p.o_world = Eigen::Vector3d(x, y, z);
  return p;
}

/// A seeded snapshot: `vossels` random vossels of edge `h`, 1-3 records each from `sources`,
/// fused RGB values under the default profile.
Snapshot MakeSnapshot(uint64_t seed, size_t vossels, double h, const std::vector<int32_t>& sources,
                      int32_t batch) {
  std::mt19937_64 rng(seed);
  std::uniform_int_distribution<int> c(-30, 29), per(1, 3);
  std::uniform_int_distribution<size_t> pick(0, sources.size() - 1);
  std::uniform_real_distribution<float> u(0.0f, 1.0f);
  Snapshot s;
  s.geometry.vossel_size_m = h;
  std::set<std::tuple<int, int, int>> seen;
  while (s.geometry.coord.size() < vossels) {
    const int x = c(rng), y = c(rng), z = c(rng);
    if (seen.insert({x, y, z}).second) s.geometry.coord.emplace_back(x, y, z);
  }
  for (size_t v = 0; v < vossels; ++v) {
    s.geometry.point_count.push_back(1 + static_cast<int32_t>(v % 17));
    s.geometry.centroid_m.emplace_back(u(rng), u(rng), u(rng));
    s.geometry.normal.emplace_back(0.0f, 0.0f, 1.0f);
  }
  records::CanonicalizeVosselOrder(s.geometry);
  const size_t n = s.geometry.size();
  for (size_t v = 0; v < n; ++v) {
    const int k = per(rng);
    for (int j = 0; j < k; ++j) {
      s.records.vossel.push_back(static_cast<int32_t>(v));
      s.records.scan.push_back(sources[pick(rng)]);
      s.records.modality.push_back(static_cast<int8_t>(Modality::kRgb));
      for (int ch = 0; ch < records::kValueChannels; ++ch) s.records.value.push_back(u(rng));
      s.records.range_m.push_back(1.0f + 20.0f * u(rng));
      s.records.cos_inc.push_back(u(rng));
      s.records.foot_major_m.push_back(0.01f * u(rng));
      s.records.foot_minor_m.push_back(0.01f * u(rng));
      s.records.uv_px.push_back(4096.0f * u(rng));
      s.records.uv_px.push_back(2048.0f * u(rng));
      s.records.vis.push_back(u(rng));
      for (int f = 0; f < records::kConfidenceCount; ++f) s.records.conf.push_back(u(rng));
      s.records.flags.push_back(0);
      s.records.batch.push_back(batch);
    }
  }
  s.records.SortByVossel();
  s.fused.profile = "default";
  records::FusedModality& rgb = s.fused.by_modality[Modality::kRgb];
  rgb.channels = 3;
  for (size_t v = 0; v < n; ++v) {
    for (int ch = 0; ch < 3; ++ch) rgb.value.push_back(u(rng));
    rgb.weight.push_back(v % 4 == 0 ? 0.0f : u(rng) + 0.1f);
    rgb.uncertainty.push_back(u(rng));
  }
  for (size_t v = 0; v < n; ++v) {
    if (rgb.weight[v] == 0.0f) {
      rgb.value[3 * v] = rgb.value[3 * v + 1] = rgb.value[3 * v + 2] = 0.0f;
      rgb.uncertainty[v] = 0.0f;
    }
  }
  return s;
}

/// A scan with one LiDAR source and one panorama source, ids taken from the store.
ScanInfo MakeScan(ProjectStore& store, const std::string& name, double x) {
  ScanInfo scan;
  scan.name = name;
  scan.rig = "rig-a";
  scan.captured_utc = "2026-01-02T03:04:05Z";
  scan.pose = PoseAt(x, 2.0, 1.5, 0.3);
  scan.batch = *store.NextBatchId();
  const int32_t first = *store.NextSourceId();
  SourceInfo lidar;
  lidar.id = first;
  lidar.name = "lidar";
  lidar.modality = Modality::kLidar;
  lidar.pose = scan.pose;
  lidar.blob_sha256 = *store.PutBlob("points of " + name);
  lidar.divergence_rad = 3e-4;
  lidar.point_count = 1234;
  SourceInfo pano;
  pano.id = first + 1;
  pano.name = "pano0";
  pano.modality = Modality::kRgb;
  pano.pose = PoseAt(x, 2.0, 1.7, -0.2);
  pano.blob_sha256 = *store.PutBlob("image of " + name);
  pano.width_px = 8192;
  pano.height_px = 4096;
  scan.sources = {lidar, pano};
  return scan;
}

std::vector<int32_t> SourceIds(const ScanInfo& scan) {
  std::vector<int32_t> ids;
  for (const SourceInfo& s : scan.sources) ids.push_back(s.id);
  return ids;
}

/// Kept versions of the store.
std::set<int64_t> KeptVersions(const ProjectStore& store) {
  std::set<int64_t> out;
  const std::vector<VersionInfo> versions = *store.ListVersions();
  for (const VersionInfo& v : versions) out.insert(v.version);
  return out;
}

/// Names of the files in `dir` (objects or blobs).
std::set<std::string> FilesIn(const fs::path& dir) {
  std::set<std::string> names;
  for (const auto& e : fs::directory_iterator(dir)) names.insert(e.path().filename().string());
  return names;
}

/// Every object the kept versions' manifests reference.
std::set<std::string> ReferencedObjects(const ProjectStore& store) {
  std::set<std::string> out;
  for (int64_t v : KeptVersions(store)) {
    const Manifest m = *store.LoadManifest(v);
    for (const auto& [key, layers] : m.tiles) {
      for (const auto& [layer, e] : layers) out.insert(e.object);
    }
    for (const auto& [source, e] : m.reach) out.insert(e.object);
  }
  return out;
}

/// Commits `snap` whole (every tile written) with `scan` added.
absl::StatusOr<int64_t> CommitScan(ProjectStore& store, const Snapshot& snap, const ScanInfo& scan) {
  CommitPlan plan;
  plan.made_by = "ingest scan " + scan.name;
  plan.replace_all = true;
  plan.add_scan = scan;
  return store.Commit(snap, plan);
}

void ExpectSnapshotsEqual(const Snapshot& a, const Snapshot& b) {
  EXPECT_EQ(a.geometry.coord, b.geometry.coord);
  EXPECT_EQ(a.geometry.point_count, b.geometry.point_count);
  EXPECT_EQ(a.geometry.centroid_m, b.geometry.centroid_m);
  EXPECT_EQ(a.records.vossel, b.records.vossel);
  EXPECT_EQ(a.records.scan, b.records.scan);
  EXPECT_EQ(a.records.batch, b.records.batch);
  ASSERT_EQ(a.records.uv_px.size(), b.records.uv_px.size());
  for (size_t i = 0; i < a.records.uv_px.size(); ++i) {
    // 16-bit steps of 16384/65535 px: |Δ| ≤ 0.125 px
    ASSERT_NEAR(a.records.uv_px[i], b.records.uv_px[i], 0.1251);
  }
  ASSERT_EQ(a.records.range_m.size(), b.records.range_m.size());
  for (size_t i = 0; i < a.records.range_m.size(); ++i) {
    // half codec: relative error ≤ 2⁻¹¹ (record_grid_test states the full precision table)
    ASSERT_NEAR(a.records.range_m[i], b.records.range_m[i], a.records.range_m[i] * 4.9e-4);
  }
  ASSERT_EQ(a.fused.by_modality.count(Modality::kRgb), 1u);
  ASSERT_EQ(b.fused.by_modality.count(Modality::kRgb), 1u);
  EXPECT_EQ(a.fused.by_modality.at(Modality::kRgb).value,
            b.fused.by_modality.at(Modality::kRgb).value);
  EXPECT_EQ(a.fused.by_modality.at(Modality::kRgb).weight,
            b.fused.by_modality.at(Modality::kRgb).weight);
}

// Claim: create → two commits → reopen restores HEAD, scans, sources and snapshot contents.
TEST(ProjectStoreTest, CommitTwoVersionsThenReopen) {
  const fs::path root = TestRoot("reopen");
  const fs::path dir = root / "site-a";
  ProjectSettings settings;
  settings.vossel_size_m = 0.05;
  settings.description = "two commits";
  absl::StatusOr<std::unique_ptr<ProjectStore>> store = ProjectStore::Create(dir, "site-a",
                                                                             settings);
  ASSERT_TRUE(store.ok()) << store.status();
  EXPECT_EQ((*store)->head_version(), 0);
  absl::StatusOr<std::shared_ptr<const Snapshot>> empty = (*store)->LoadSnapshot(0);
  ASSERT_TRUE(empty.ok()) << empty.status();
  EXPECT_EQ((*empty)->geometry.size(), 0u);
  EXPECT_DOUBLE_EQ((*empty)->geometry.vossel_size_m, 0.05);
  ASSERT_TRUE((*empty)->geometry.index_grid);
  EXPECT_EQ((*empty)->geometry.index_grid->activeVoxelCount(), 0u);

  const ScanInfo scan_a = MakeScan(**store, "scan-a", 1.0);
  const Snapshot snap1 = MakeSnapshot(1, 3000, 0.05, SourceIds(scan_a), scan_a.batch);
  absl::StatusOr<int64_t> v1 = CommitScan(**store, snap1, scan_a);
  ASSERT_TRUE(v1.ok()) << v1.status();
  EXPECT_EQ(*v1, 1);
  const ScanInfo scan_b = MakeScan(**store, "scan-b", 4.0);
  EXPECT_EQ(scan_b.sources[0].id, 3);
  EXPECT_EQ(scan_b.batch, scan_a.batch + 1);
  const Snapshot snap2 = MakeSnapshot(2, 5000, 0.05, {1, 2, 3, 4}, scan_b.batch);
  absl::StatusOr<int64_t> v2 = CommitScan(**store, snap2, scan_b);
  ASSERT_TRUE(v2.ok()) << v2.status();
  EXPECT_EQ(*v2, 2);
  store->reset();

  absl::StatusOr<std::unique_ptr<ProjectStore>> reopened = ProjectStore::Open(dir);
  ASSERT_TRUE(reopened.ok()) << reopened.status();
  ProjectStore& s = **reopened;
  EXPECT_EQ(s.name(), "site-a");
  EXPECT_EQ(s.settings().description, "two commits");
  EXPECT_DOUBLE_EQ(s.settings().vossel_size_m, 0.05);
  EXPECT_EQ(s.head_version(), 2);
  absl::StatusOr<VersionInfo> info = s.HeadInfo();
  ASSERT_TRUE(info.ok());
  EXPECT_EQ(info->vossel_count, int64_t(snap2.geometry.size()));
  EXPECT_EQ(info->record_count, int64_t(snap2.records.size()));

  absl::StatusOr<std::vector<ScanInfo>> scans = s.ListScans();
  ASSERT_TRUE(scans.ok()) << scans.status();
  ASSERT_EQ(scans->size(), 2u);
  for (size_t i = 0; i < 2; ++i) {
    const ScanInfo& want = i == 0 ? scan_a : scan_b;
    const ScanInfo& got = (*scans)[i];
    EXPECT_EQ(got.name, want.name);
    EXPECT_EQ(got.rig, want.rig);
    EXPECT_EQ(got.captured_utc, want.captured_utc);
    EXPECT_EQ(got.version, int64_t(i + 1));
    EXPECT_EQ(got.batch, want.batch);
    EXPECT_FALSE(got.created_utc.empty());
    EXPECT_TRUE(got.pose.o_world.isApprox(want.pose.o_world, 1e-15));
    EXPECT_TRUE(got.pose.q_world_sensor.isApprox(want.pose.q_world_sensor, 1e-15));
    ASSERT_EQ(got.sources.size(), 2u);
    for (size_t j = 0; j < 2; ++j) {
      EXPECT_EQ(got.sources[j].id, want.sources[j].id);
      EXPECT_EQ(got.sources[j].scan_id, got.id);
      EXPECT_EQ(got.sources[j].name, want.sources[j].name);
      EXPECT_EQ(got.sources[j].modality, want.sources[j].modality);
      EXPECT_EQ(got.sources[j].blob_sha256, want.sources[j].blob_sha256);
      EXPECT_EQ(got.sources[j].width_px, want.sources[j].width_px);
      EXPECT_EQ(got.sources[j].divergence_rad, want.sources[j].divergence_rad);
      EXPECT_EQ(got.sources[j].point_count, want.sources[j].point_count);
      EXPECT_TRUE(got.sources[j].pose.o_world.isApprox(want.sources[j].pose.o_world, 1e-15));
    }
  }
  EXPECT_TRUE(*s.HasScan("scan-a"));
  EXPECT_FALSE(*s.HasScan("scan-c"));
  EXPECT_EQ(*s.ReadBlob(scan_a.sources[0].blob_sha256), "points of scan-a");

  for (const auto& [v, want] : {std::pair<int64_t, const Snapshot*>{1, &snap1}, {2, &snap2}}) {
    absl::StatusOr<std::shared_ptr<const Snapshot>> got = s.LoadSnapshot(v);
    ASSERT_TRUE(got.ok()) << got.status();
    EXPECT_EQ((*got)->version, v);
    ExpectSnapshotsEqual(**got, *want);
  }
  EXPECT_EQ(s.LoadSnapshot(3).status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(s.LoadSnapshot(-1).status().code(), absl::StatusCode::kInvalidArgument);
  absl::StatusOr<std::vector<records::AttributeInfo>> attrs = s.InspectRecords(2);
  ASSERT_TRUE(attrs.ok()) << attrs.status();
  EXPECT_EQ(attrs->size(), 13u);
  EXPECT_EQ(KeptVersions(s), (std::set<int64_t>{1, 2}));
  // Every layer of every tile is an object of the manifest; the objects are exactly those.
  const Manifest m2 = *s.LoadManifest(2);
  EXPECT_GE(m2.tiles.size(), 2u);  // coordinates span [-30, 29]: more than one 64³ tile
  for (const auto& [key, layers] : m2.tiles) {
    EXPECT_EQ(layers.size(), 3u) << tiles::ToString(key);
  }
  EXPECT_EQ(FilesIn(dir / "objects"), ReferencedObjects(s));
  EXPECT_EQ(info->made_by, "ingest scan scan-b");
  EXPECT_EQ(info->tile_count, int64_t(m2.tiles.size()));
  std::printf("two commits: v1 %zu vossels / %zu records, v2 %zu vossels / %zu records; "
              "reopened HEAD %lld with %zu scans\n",
              snap1.geometry.size(), snap1.records.size(), snap2.geometry.size(),
              snap2.records.size(), static_cast<long long>(s.head_version()), scans->size());
  fs::remove_all(root);
}

// Claim: a duplicate scan name is ALREADY_EXISTS and changes nothing (bad input never changes a
// project); a bad project name is INVALID_ARGUMENT; a missing project is NOT_FOUND.
TEST(ProjectStoreTest, RejectsBadInputWithoutChanges) {
  const fs::path root = TestRoot("bad");
  EXPECT_EQ(ProjectStore::Create(root / "x", "Bad Name", {}).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(ProjectStore::Create(root / "x", "-dash", {}).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(ProjectStore::Open(root / "nope").status().code(), absl::StatusCode::kNotFound);
  auto store = ProjectStore::Create(root / "p", "p", {});
  ASSERT_TRUE(store.ok()) << store.status();
  EXPECT_EQ(ProjectStore::Create(root / "p", "p", {}).status().code(),
            absl::StatusCode::kAlreadyExists);
  const ScanInfo scan = MakeScan(**store, "s1", 0.0);
  ASSERT_TRUE(CommitScan(**store, MakeSnapshot(3, 500, 0.02, SourceIds(scan), scan.batch), scan)
                  .ok());
  ScanInfo again = MakeScan(**store, "s1", 0.0);
  absl::StatusOr<int64_t> dup =
      CommitScan(**store, MakeSnapshot(4, 600, 0.02, SourceIds(again), again.batch), again);
  EXPECT_EQ(dup.status().code(), absl::StatusCode::kAlreadyExists);
  std::printf("duplicate scan: %s\n", dup.status().ToString().c_str());
  ScanInfo reused_ids = MakeScan(**store, "s2", 0.0);
  reused_ids.sources[0].id = scan.sources[0].id;
  EXPECT_EQ(CommitScan(**store, MakeSnapshot(4, 600, 0.02, {1}, again.batch), reused_ids)
                .status()
                .code(),
            absl::StatusCode::kAlreadyExists);
  Snapshot wrong_h = MakeSnapshot(5, 100, 0.05, SourceIds(again), again.batch);
  again.name = "s3";
  EXPECT_EQ(CommitScan(**store, wrong_h, again).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ((*store)->head_version(), 1);
  EXPECT_EQ((*store)->ListScans()->size(), 1u);
  EXPECT_EQ(KeptVersions(**store), (std::set<int64_t>{1}));
  fs::remove_all(root);
}

// Claim: a commit that fails midway (injected IO failure after each stage) leaves HEAD, the
// catalog and the versions directory as they were; the next commit then succeeds.
TEST(ProjectStoreTest, FailedCommitLeavesHeadAndCatalogUnchanged) {
  const fs::path root = TestRoot("fail");
  auto store = ProjectStore::Create(root / "p", "p", {});
  ASSERT_TRUE(store.ok());
  ProjectStore& s = **store;
  const ScanInfo first = MakeScan(s, "first", 0.0);
  ASSERT_TRUE(CommitScan(s, MakeSnapshot(6, 800, 0.02, SourceIds(first), first.batch), first).ok());
  int failures = 0;
  const std::set<std::string> objects_before = FilesIn(root / "p" / "objects");
  for (auto stage : {ProjectStore::CommitStage::kAfterObjects,
                     ProjectStore::CommitStage::kAfterCatalog}) {
    const ScanInfo scan = MakeScan(s, "doomed", 1.0);
    s.InjectCommitFailureForTesting(stage, /*simulate_crash=*/false);
    absl::StatusOr<int64_t> v =
        CommitScan(s, MakeSnapshot(7, 900, 0.02, SourceIds(scan), scan.batch), scan);
    EXPECT_FALSE(v.ok());
    failures += !v.ok();
    EXPECT_EQ(s.head_version(), 1);
    EXPECT_FALSE(*s.HasScan("doomed"));
    EXPECT_EQ(s.ListScans()->size(), 1u);
    EXPECT_EQ(*s.NextSourceId(), 3);
    EXPECT_EQ(KeptVersions(s), (std::set<int64_t>{1}));
    EXPECT_EQ(FilesIn(root / "p" / "objects"), objects_before) << "no orphan object survives";
    std::ifstream head(root / "p" / "HEAD");
    int64_t on_disk = -1;
    head >> on_disk;
    EXPECT_EQ(on_disk, 1);
  }
  const ScanInfo ok_scan = MakeScan(s, "doomed", 1.0);
  absl::StatusOr<int64_t> v =
      CommitScan(s, MakeSnapshot(8, 900, 0.02, SourceIds(ok_scan), ok_scan.batch), ok_scan);
  ASSERT_TRUE(v.ok()) << v.status();
  EXPECT_EQ(*v, 2);
  std::printf("failed commits: %d injected failures left HEAD at 1; next commit made v%lld\n",
              failures, static_cast<long long>(*v));
  fs::remove_all(root);
}

// Claim: after a crash at any point of a commit, Open trusts HEAD: it drops catalog rows newer
// than HEAD and deletes stray temp dirs and version dirs newer than HEAD.
TEST(ProjectStoreTest, OpenRecoversFromCrashedCommit) {
  const fs::path root = TestRoot("crash");
  const fs::path dir = root / "p";
  {
    auto store = ProjectStore::Create(dir, "p", {});
    ASSERT_TRUE(store.ok());
    const ScanInfo first = MakeScan(**store, "first", 0.0);
    ASSERT_TRUE(
        CommitScan(**store, MakeSnapshot(9, 700, 0.02, SourceIds(first), first.batch), first).ok());
    const ScanInfo crashed = MakeScan(**store, "crashed", 1.0);
    (*store)->BeginOperation({"retry-me", "ingest", "crashed"});  // recorded with its version
    (*store)->InjectCommitFailureForTesting(ProjectStore::CommitStage::kAfterCatalog,
                                            /*simulate_crash=*/true);
    EXPECT_FALSE(CommitScan(**store,
                            MakeSnapshot(10, 700, 0.02, SourceIds(crashed), crashed.batch),
                            crashed)
                     .ok());
    EXPECT_TRUE(*(*store)->HasScan("crashed")) << "the simulated crash must leave its rows";
    EXPECT_TRUE((*(*store)->FindOperation("retry-me")).has_value());
    (*store)->EndOperation();
  }
  // More debris: a half-written staging file, an object nothing references, a partial blob.
  std::ofstream(dir / "objects" / ".tmp-deadbeef") << "partial";
  std::ofstream(dir / "objects" / std::string(64, 'e')) << "orphan";
  std::ofstream(dir / "blobs" / ".tmp-abc-123") << "partial blob";

  auto store = ProjectStore::Open(dir);
  ASSERT_TRUE(store.ok()) << store.status();
  EXPECT_EQ((*store)->head_version(), 1);
  EXPECT_FALSE(*(*store)->HasScan("crashed"));
  EXPECT_EQ((*store)->ListScans()->size(), 1u);
  EXPECT_EQ(KeptVersions(**store), (std::set<int64_t>{1}));
  EXPECT_EQ(FilesIn(dir / "objects"), ReferencedObjects(**store));
  EXPECT_FALSE(fs::exists(dir / "blobs" / ".tmp-abc-123"));
  EXPECT_EQ((*store)->HeadInfo()->version, 1);
  // A change that did not reach HEAD is not committed: its request id is free for the retry.
  EXPECT_FALSE((*(*store)->FindOperation("retry-me")).has_value());
  const ScanInfo retry = MakeScan(**store, "crashed", 1.0);
  EXPECT_EQ(retry.sources[0].id, 3);
  absl::StatusOr<int64_t> v = CommitScan(**store, 
      MakeSnapshot(11, 700, 0.02, SourceIds(retry), retry.batch), retry);
  ASSERT_TRUE(v.ok()) << v.status();
  EXPECT_EQ(*v, 2);
  std::printf("crash recovery: HEAD 1 kept, version 2's rows, its objects and debris removed, "
              "retry -> v%lld\n",
              static_cast<long long>(*v));
  fs::remove_all(root);
}

// Claim: blobs are addressed by their sha256 (FIPS 180-2 test vector "abc"), storing the same
// bytes twice is idempotent, and lookups validate the id.
TEST(ProjectStoreTest, BlobsAreContentAddressedAndIdempotent) {
  const fs::path root = TestRoot("blobs");
  auto store = ProjectStore::Create(root / "p", "p", {});
  ASSERT_TRUE(store.ok());
  absl::StatusOr<std::string> a = (*store)->PutBlob("abc");
  ASSERT_TRUE(a.ok()) << a.status();
  EXPECT_EQ(*a, "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
  EXPECT_EQ(*(*store)->PutBlob("abc"), *a);
  const std::string big(3 << 20, '\x7f');
  absl::StatusOr<std::string> b = (*store)->PutBlob(big);
  ASSERT_TRUE(b.ok());
  EXPECT_EQ(*(*store)->ReadBlob(*b), big);
  EXPECT_EQ(*(*store)->ReadBlob(*a), "abc");
  size_t files = 0;
  for (const auto& e : fs::directory_iterator(root / "p" / "blobs")) files += e.is_regular_file();
  EXPECT_EQ(files, 2u);
  EXPECT_EQ((*store)->ReadBlob("../HEAD").status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ((*store)->ReadBlob(std::string(64, 'a')).status().code(),
            absl::StatusCode::kNotFound);
  std::printf("blobs: sha256(\"abc\") = %s; 3 puts -> %zu files\n", a->c_str(), files);
  fs::remove_all(root);
}

// Claim: retention keeps HEAD, the `keep_versions` versions before it and pinned ones; the
// catalog rows of older versions stay, marked pruned, and every object no kept version
// references is removed (and none that one does).
TEST(ProjectStoreTest, RetentionPrunesOldVersions) {
  const fs::path root = TestRoot("retention");
  ProjectSettings settings;
  settings.keep_versions = 2;
  auto store = ProjectStore::Create(root / "p", "p", settings);
  ASSERT_TRUE(store.ok());
  for (int i = 0; i < 5; ++i) {
    const ScanInfo scan = MakeScan(**store, "scan-" + std::to_string(i), i);
    ASSERT_TRUE(CommitScan(**store, MakeSnapshot(20 + i, 300, 0.02, SourceIds(scan), scan.batch),
                           scan)
                    .ok());
    if (i == 0) ASSERT_TRUE((*store)->SetPinned(1, true).ok());
  }
  EXPECT_EQ((*store)->head_version(), 5);
  EXPECT_EQ(KeptVersions(**store), (std::set<int64_t>{1, 3, 4, 5}));
  EXPECT_EQ((*store)->LoadSnapshot(2).status().code(), absl::StatusCode::kNotFound);
  EXPECT_TRUE((*store)->LoadSnapshot(3).ok());
  EXPECT_TRUE((*store)->LoadSnapshot(1).ok()) << "a pinned version survives retention";
  EXPECT_EQ(FilesIn(root / "p" / "objects"), ReferencedObjects(**store));
  EXPECT_EQ((*store)->ListScans()->size(), 5u);

  sqlite3* db = nullptr;
  ASSERT_EQ(sqlite3_open_v2((root / "p" / "catalog.sqlite").c_str(), &db, SQLITE_OPEN_READONLY,
                            nullptr),
            SQLITE_OK);
  sqlite3_stmt* st = nullptr;
  sqlite3_prepare_v2(db, "SELECT version, pruned FROM versions ORDER BY version", -1, &st,
                     nullptr);
  std::vector<std::pair<int, int>> rows;
  while (sqlite3_step(st) == SQLITE_ROW) {
    rows.emplace_back(sqlite3_column_int(st, 0), sqlite3_column_int(st, 1));
  }
  sqlite3_finalize(st);
  sqlite3_close(db);
  EXPECT_EQ(rows, (std::vector<std::pair<int, int>>{{1, 0}, {2, 1}, {3, 0}, {4, 0}, {5, 0}}));
  std::printf("retention keep_versions=2, v1 pinned: after 5 commits, kept {1,3,4,5}; row 2 "
              "pruned; %zu objects on disk, all referenced\n",
              FilesIn(root / "p" / "objects").size());
  fs::remove_all(root);
}

// Claim: readers (LoadSnapshot, ListScans, ReadBlob) run concurrently with one writer and
// always see a complete committed version.
TEST(ProjectStoreTest, ReadersRunDuringCommits) {
  const fs::path root = TestRoot("concurrent");
  auto store = ProjectStore::Create(root / "p", "p", {});
  ASSERT_TRUE(store.ok());
  ProjectStore& s = **store;
  std::atomic<bool> done{false};
  std::atomic<int> reads{0}, bad{0};
  std::thread reader([&] {
    while (!done) {
      const int64_t v = s.head_version();
      auto snap = s.LoadSnapshot(v);
      auto scans = s.ListScans();
      if (!snap.ok() || !scans.ok() || (*snap)->version != v ||
          ((*snap)->records.size() == 0 && v > 0) || int64_t(scans->size()) < v) {
        ++bad;
      }
      ++reads;
    }
  });
  for (int i = 0; i < 4; ++i) {
    const ScanInfo scan = MakeScan(s, "c" + std::to_string(i), i);
    ASSERT_TRUE(CommitScan(s, MakeSnapshot(40 + i, 2000, 0.02, SourceIds(scan), scan.batch), scan)
                    .ok());
  }
  done = true;
  reader.join();
  EXPECT_EQ(bad.load(), 0);
  EXPECT_GT(reads.load(), 0);
  std::printf("concurrent: %d reads during 4 commits, %d inconsistent\n", reads.load(),
              bad.load());
  fs::remove_all(root);
}

// Claim: a commit writes only the tiles it changed; every other tile of the new manifest is
// the previous version's object, shared, and reads back as it was. Objects are content-
// addressed and tile files deterministic, so the changed tile's fused layer, whose values the
// test leaves as they were, is the same object too.
TEST(ProjectStoreTest, CommitWritesOnlyChangedTiles) {
  const fs::path root = TestRoot("tiles");
  auto store = ProjectStore::Create(root / "p", "p", {});
  ASSERT_TRUE(store.ok());
  ProjectStore& s = **store;
  const ScanInfo scan = MakeScan(s, "a", 0.0);
  Snapshot snap = MakeSnapshot(50, 4000, 0.02, SourceIds(scan), scan.batch);
  ASSERT_TRUE(CommitScan(s, snap, scan).ok());
  const Manifest m1 = *s.LoadManifest(1);
  ASSERT_GE(m1.tiles.size(), 4u);
  // Change the records of one tile only.
  const tiles::TileKey target = m1.tiles.begin()->first;
  for (size_t i = 0; i < snap.records.size(); ++i) {
    if (tiles::TileOf(snap.geometry.coord[size_t(snap.records.vossel[i])], 64) == target) {
      snap.records.vis[i] = 0.25f;
    }
  }
  CommitPlan plan;
  plan.made_by = "test: one tile";
  plan.record_tiles = {target};
  absl::StatusOr<int64_t> v2 = s.Commit(snap, plan);
  ASSERT_TRUE(v2.ok()) << v2.status();
  // Its times say what it did: records (and the fused layer beside them) encoded and put, no
  // geometry; the tiles' steps took no more thread time than their wall time on every thread.
  const CommitTimes t = s.LastCommitTimes();
  EXPECT_EQ(t.geometry_s, 0.0);
  EXPECT_GT(t.records_s, 0.0);
  EXPECT_GT(t.put_s, 0.0);
  EXPECT_LE(t.cut_s + t.records_s + t.fused_s + t.put_s,
            t.tiles_wall_s * double(tbb::this_task_arena::max_concurrency()) + 1e-3);
  const Manifest m2 = *s.LoadManifest(*v2);
  ASSERT_EQ(m2.tiles.size(), m1.tiles.size());
  int shared = 0, rewritten = 0;
  for (const auto& [key, layers] : m2.tiles) {
    for (const auto& [layer, e] : layers) {
      const bool same = m1.tiles.at(key).at(layer).object == e.object;
      if (key == target && layer == kLayerRecords) {
        EXPECT_FALSE(same) << layer;
        ++rewritten;
      } else {
        EXPECT_TRUE(same) << tiles::ToString(key) << " " << layer;
        ++shared;
      }
    }
  }
  const VersionInfo info = *s.HeadInfo();
  EXPECT_LT(info.bytes_written, info.bytes_total / 2);
  absl::StatusOr<std::shared_ptr<const Snapshot>> back = s.LoadSnapshot(*v2);
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ((*back)->records.vis.size(), snap.records.vis.size());
  size_t quarter = 0;
  for (float v : (*back)->records.vis) quarter += std::abs(v - 0.25f) <= 0.5f / 255.0f;  // ufxpt8
  EXPECT_GE(quarter, m1.tiles.at(target).at(kLayerRecords).records);
  std::printf("one-tile commit: %d objects rewritten, %d shared; %lld of %lld bytes written\n",
              rewritten, shared, static_cast<long long>(info.bytes_written),
              static_cast<long long>(info.bytes_total));
  fs::remove_all(root);
}

// Claim: tiles put group by group (PutTiles, a rebuild within a memory budget) commit as one
// version equal object for object to a commit of the whole snapshot; a failed commit of them
// leaves HEAD and the catalog as they were and no orphan object; put tiles commit only as a
// whole new version.
TEST(ProjectStoreTest, TilesPutInGroupsCommitAsOneVersion) {
  const fs::path root = TestRoot("put-tiles");
  auto whole_store = ProjectStore::Create(root / "whole", "whole", {});
  auto store = ProjectStore::Create(root / "p", "p", {});
  ASSERT_TRUE(whole_store.ok() && store.ok());
  ProjectStore& s = **store;
  const ScanInfo first = MakeScan(s, "first", 0.0);
  ASSERT_TRUE(CommitScan(s, MakeSnapshot(60, 500, 0.02, SourceIds(first), first.batch), first)
                  .ok());
  const ScanInfo scan = MakeScan(s, "a", 1.0);
  const Snapshot snap = MakeSnapshot(61, 4000, 0.02, SourceIds(scan), scan.batch);
  ASSERT_TRUE(CommitScan(**whole_store, snap, scan).ok());  // the same tiles, written whole

  // The tiles in three groups, each put from a snapshot holding that group's records alone.
  const std::vector<tiles::TileKey> tile_of = tiles::TilesOfVossels(snap.geometry, 64);
  const std::set<tiles::TileKey> all(tile_of.begin(), tile_of.end());
  ASSERT_GE(all.size(), 6u);
  std::vector<std::set<tiles::TileKey>> groups(3);
  size_t t = 0;
  for (const tiles::TileKey& key : all) groups[t++ % 3].insert(key);
  auto put_all = [&]() {
    CommitPlan plan;
    plan.made_by = "test: put in groups";
    plan.replace_all = true;
    plan.add_scan = scan;
    for (const std::set<tiles::TileKey>& group : groups) {
      Snapshot part;
      part.geometry = snap.geometry;
      part.fused = snap.fused;
      std::vector<size_t> mine;
      for (size_t i = 0; i < snap.records.size(); ++i) {
        if (group.count(tile_of[size_t(snap.records.vossel[i])])) mine.push_back(i);
      }
      part.records = snap.records.Select(mine);
      auto put = s.PutTiles(part, group);
      EXPECT_TRUE(put.ok()) << put.status();
      if (put.ok()) plan.put_tiles.insert(put->begin(), put->end());
    }
    return plan;
  };
  Snapshot shell;  // geometry alone: the records are in the put tiles
  shell.geometry = snap.geometry;
  shell.records_partial = true;

  // A failure after the objects: HEAD, catalog and objects as before the puts.
  const std::set<std::string> objects_before = FilesIn(root / "p" / "objects");
  CommitPlan plan = put_all();
  s.InjectCommitFailureForTesting(ProjectStore::CommitStage::kAfterObjects, false);
  EXPECT_FALSE(s.Commit(shell, plan).ok());
  EXPECT_EQ(s.head_version(), 1);
  EXPECT_EQ(KeptVersions(s), std::set<int64_t>{1});
  EXPECT_EQ(FilesIn(root / "p" / "objects"), objects_before) << "no orphan object survives";

  // Put tiles make a whole version and nothing else.
  plan = put_all();
  CommitPlan partial = plan;
  partial.replace_all = false;
  EXPECT_TRUE(absl::IsInvalidArgument(s.Commit(shell, partial).status()));
  partial = plan;
  partial.record_tiles = {*all.begin()};
  EXPECT_TRUE(absl::IsInvalidArgument(s.Commit(shell, partial).status()));

  absl::StatusOr<int64_t> v = s.Commit(shell, plan);
  ASSERT_TRUE(v.ok()) << v.status();
  const Manifest m = *s.LoadManifest(*v);
  const Manifest w = *(*whole_store)->LoadManifest(1);
  ASSERT_EQ(m.tiles.size(), all.size());
  ASSERT_EQ(m.tiles.size(), w.tiles.size());
  int objects = 0;
  for (const auto& [key, layers] : w.tiles) {
    for (const auto& [layer, e] : layers) {
      ++objects;
      ASSERT_TRUE(m.tiles.count(key) && m.tiles.at(key).count(layer)) << tiles::ToString(key);
      EXPECT_EQ(m.tiles.at(key).at(layer).object, e.object) << tiles::ToString(key) << layer;
    }
  }
  EXPECT_EQ(s.HeadInfo()->record_count, int64_t(snap.records.size()));
  EXPECT_EQ(s.HeadInfo()->vossel_count, int64_t(snap.geometry.size()));
  EXPECT_EQ(FilesIn(root / "p" / "objects"), ReferencedObjects(s));
  std::printf("tiles put in 3 groups: %d objects, every one the whole commit's\n", objects);
  fs::remove_all(root);
}

// Claim: a catalog of an earlier schema (2: before profiles and scan lives) opens migrated,
// keeps its versions and scans (and the origin 0 they were stored in), and takes profiles and rollbacks afterwards.
TEST(ProjectStoreTest, OpensAndMigratesASchema2Catalog) {
  const fs::path root = TestRoot("migrate");
  {
    auto store = ProjectStore::Create(root / "p", "p", {});
    ASSERT_TRUE(store.ok());
    for (const char* name : {"a", "b"}) {
      const ScanInfo scan = MakeScan(**store, name, name[0] == 'a' ? 0.0 : 3.0);
      ASSERT_TRUE(CommitScan(**store, MakeSnapshot(3, 400, 0.02, SourceIds(scan), scan.batch), scan).ok());
    }
  }
  {  // Take the catalog back to schema 2, as an earlier vasl wrote it.
    sqlite3* db = nullptr;
    ASSERT_EQ(sqlite3_open((root / "p" / "catalog.sqlite").c_str(), &db), SQLITE_OK);
    char* err = nullptr;
    const int rc = sqlite3_exec(db,
        "BEGIN; DROP TABLE profiles; DROP TABLE scan_lives; DROP TABLE renders; "
        "DROP TABLE operations; DROP TABLE calibration; DROP TABLE visual_references; "
        "DROP TABLE lens_maps; "
        "ALTER TABLE sources DROP COLUMN camera; ALTER TABLE sources DROP COLUMN mask_sha256; "
        "ALTER TABLE project DROP COLUMN active_profile; "
        "ALTER TABLE project DROP COLUMN origin_fixed; ALTER TABLE project DROP COLUMN origin_x; "
        "ALTER TABLE project DROP COLUMN origin_y; ALTER TABLE project DROP COLUMN origin_z; "
        "CREATE UNIQUE INDEX live_scan_names ON scans(name) WHERE deleted_in IS NULL; "
        "UPDATE schema_version SET version = 2; COMMIT;", nullptr, nullptr, &err);
    EXPECT_EQ(rc, SQLITE_OK) << (err ? err : "");
    sqlite3_free(err);
    sqlite3_close(db);
  }
  auto store = ProjectStore::Open(root / "p");
  ASSERT_TRUE(store.ok()) << store.status();
  EXPECT_EQ((*store)->head_version(), 2);
  EXPECT_EQ((*store)->ListScans(2)->size(), 2u);
  EXPECT_EQ((*store)->ListScans(1)->size(), 1u);
  EXPECT_TRUE(*(*store)->HasScan("a"));
  EXPECT_EQ(*(*store)->ActiveProfile(), "default");
  // A project that had scans before origins existed worked in world coordinates: origin 0.
  ASSERT_TRUE((*store)->origin().has_value());
  EXPECT_EQ(*(*store)->origin(), Eigen::Vector3d::Zero());
  auto put = (*store)->PutProfile("p1", [](int32_t r) { return absl::StrCat("revision ", r); });
  ASSERT_TRUE(put.ok()) << put.status();
  EXPECT_EQ(put->revision, 1);
  auto lens = (*store)->PutLensMap("rig", "pano", "text");
  ASSERT_TRUE(lens.ok()) << lens.status();
  EXPECT_EQ((*store)->GetLensMap(lens->id)->text, "text");
  CommitPlan back;
  back.made_by = "rollback to version 1";
  back.rollback_to = 1;
  ASSERT_TRUE((*store)->Commit(Snapshot{}, back).ok());
  EXPECT_EQ((*store)->ListScans(0)->size(), 1u);
  EXPECT_FALSE(*(*store)->HasScan("b"));
  fs::remove_all(root);
}

}  // namespace
}  // namespace vasl::store

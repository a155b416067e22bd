// VASL-MODEL §1 (vossel lattice), §6 (records), §7 (fused values) on disk: record_grid.h.
#include "lattice/records/record_grid.h"

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <map>
#include <numeric>
#include <random>
#include <set>
#include <string>
#include <tuple>
#include <vector>

#include <gtest/gtest.h>
#include <openvdb/io/File.h>
#include <openvdb/points/PointAttribute.h>
#include <openvdb/points/PointCount.h>
#include <openvdb/points/PointDataGrid.h>

#include "absl/strings/str_cat.h"
#include "lattice/memory/isa.h"
#include "lattice/records/vdb_io.h"

namespace vasl::records {
namespace {

namespace fs = std::filesystem;

fs::path TestDir(const std::string& name) {
  fs::path dir = fs::temp_directory_path() /
                 ("vasl-records-" + name + "-" + std::to_string(::getpid()));
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

/// Seeded random lattice: `n` unique coordinates in a 96³ box around the origin (negative
/// coordinates included), shuffled, with geometry arrays whose values identify their vossel.
VosselGeometry RandomGeometry(size_t n, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_int_distribution<int> c(-48, 47);
  std::set<std::tuple<int, int, int>> seen;
  VosselGeometry g;
  g.vossel_size_m = 0.02;
  while (g.coord.size() < n) {
    const int x = c(rng), y = c(rng), z = c(rng);
    if (seen.insert({x, y, z}).second) g.coord.emplace_back(x, y, z);
  }
  std::uniform_real_distribution<float> u(-1.0f, 1.0f);
  for (size_t i = 0; i < n; ++i) {
    g.point_count.push_back(static_cast<int32_t>(i));
    g.centroid_m.emplace_back(u(rng), u(rng), u(rng));
    g.normal.push_back(Eigen::Vector3f(u(rng), u(rng), u(rng)).normalized());
    g.covariance_m2.push_back({u(rng), u(rng), u(rng), u(rng), u(rng), u(rng)});
  }
  return g;
}

/// 1-6 records per vossel with every attribute drawn over its full range; every 7th record
/// has vis exactly 0.5 (the default V_min, §7).
RecordSet RandomRecords(size_t vossels, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_int_distribution<int> per(1, 6), scan(1, 40), mod(1, 5), batch(1, 12), flg(0, 3);
  std::uniform_real_distribution<float> u01(0.0f, 1.0f);
  RecordSet r;
  for (size_t v = 0; v < vossels; ++v) {
    const int k = per(rng);
    for (int j = 0; j < k; ++j) {
      r.vossel.push_back(static_cast<int32_t>(v));
      r.scan.push_back(scan(rng));
      r.modality.push_back(static_cast<int8_t>(mod(rng)));
      for (int c = 0; c < kValueChannels; ++c) r.value.push_back(4.0f * u01(rng));
      r.range_m.push_back(0.5f + 120.0f * u01(rng));
      r.cos_inc.push_back(u01(rng));
      r.foot_major_m.push_back(1e-4f + 0.05f * u01(rng));
      r.foot_minor_m.push_back(1e-4f + 0.02f * u01(rng));
      r.uv_px.push_back(16384.0f * u01(rng));
      r.uv_px.push_back(8192.0f * u01(rng));
      r.vis.push_back(r.size() % 7 == 0 ? 0.5f : u01(rng));
      for (int c = 0; c < kConfidenceCount; ++c) r.conf.push_back(u01(rng));
      r.flags.push_back(static_cast<int8_t>(flg(rng)));
      r.batch.push_back(batch(rng));
    }
  }
  r.SortByVossel();
  return r;
}

/// Largest |a - b| / scale(a) over two arrays.
template <typename Fn>
double WorstError(const std::vector<float>& a, const std::vector<float>& b, Fn&& scale) {
  double worst = 0.0;
  for (size_t i = 0; i < a.size(); ++i) {
    worst = std::max(worst, std::fabs(double(a[i]) - double(b[i])) / scale(a[i]));
  }
  return worst;
}

// Claim (records.h): SortByVossel is a stable sort by (vossel, scan, modality). Checked against
// std::stable_sort of the positions on the arrangements its paths take: records appended to
// sorted ones (merged in place), a sorted run inside (merged into new arrays), in order
// already, and tiny sets. Keys repeat (few vossels, scans and modalities), so every record
// carries its position in `batch` to show the order among equal keys.
/// `n` records of keys drawn from 41 vossels, 3 scans and 2 modalities (many equal keys), every
/// other field random; sorted by key (stably) when `sorted`.
RecordSet KeyedRecords(std::mt19937_64& rng, size_t n, bool sorted) {
  std::uniform_int_distribution<int> vossel(0, 40), scan(1, 3), mod(1, 2);
  std::uniform_real_distribution<float> u(0.0f, 1.0f);
  RecordSet r;
  for (size_t i = 0; i < n; ++i) {
    r.vossel.push_back(vossel(rng));
    r.scan.push_back(scan(rng));
    r.modality.push_back(static_cast<int8_t>(mod(rng)));
    for (int c = 0; c < kValueChannels; ++c) r.value.push_back(u(rng));
    for (auto* a : {&r.range_m, &r.cos_inc, &r.foot_major_m, &r.foot_minor_m, &r.vis}) {
      a->push_back(u(rng));
    }
    r.uv_px.push_back(u(rng));
    r.uv_px.push_back(u(rng));
    for (int c = 0; c < kConfidenceCount; ++c) r.conf.push_back(u(rng));
    r.flags.push_back(static_cast<int8_t>(i % 4));
    r.batch.push_back(0);
  }
  if (sorted) {
    std::vector<size_t> order(n);
    std::iota(order.begin(), order.end(), size_t{0});
    std::stable_sort(order.begin(), order.end(), [&r](size_t a, size_t b) {
      return std::tie(r.vossel[a], r.scan[a], r.modality[a]) <
             std::tie(r.vossel[b], r.scan[b], r.modality[b]);
    });
    r = r.Select(order);
  }
  return r;
}

/// Every array of `got` equals `want`'s.
void ExpectSameRecords(const RecordSet& got, const RecordSet& want, const std::string& what) {
  EXPECT_EQ(got.vossel, want.vossel) << what;
  EXPECT_EQ(got.scan, want.scan) << what;
  EXPECT_EQ(got.modality, want.modality) << what;
  EXPECT_EQ(got.batch, want.batch) << what << ": equal keys out of order";
  EXPECT_EQ(got.value, want.value) << what;
  EXPECT_EQ(got.range_m, want.range_m) << what;
  EXPECT_EQ(got.cos_inc, want.cos_inc) << what;
  EXPECT_EQ(got.foot_major_m, want.foot_major_m) << what;
  EXPECT_EQ(got.foot_minor_m, want.foot_minor_m) << what;
  EXPECT_EQ(got.uv_px, want.uv_px) << what;
  EXPECT_EQ(got.vis, want.vis) << what;
  EXPECT_EQ(got.conf, want.conf) << what;
  EXPECT_EQ(got.flags, want.flags) << what;
}

/// `r` stably sorted by (vossel, scan, modality), by index.
RecordSet StablySorted(const RecordSet& r) {
  std::vector<size_t> order(r.size());
  std::iota(order.begin(), order.end(), size_t{0});
  std::stable_sort(order.begin(), order.end(), [&r](size_t a, size_t b) {
    return std::tie(r.vossel[a], r.scan[a], r.modality[a]) <
           std::tie(r.vossel[b], r.scan[b], r.modality[b]);
  });
  return r.Select(order);
}

TEST(RecordSetTest, SortByVosselIsAStableSortByItsKey) {
  std::mt19937_64 rng(5);
  auto records = [&rng](size_t n, bool sorted) { return KeyedRecords(rng, n, sorted); };
  auto check = [](RecordSet r, const std::string& what) {
    for (size_t i = 0; i < r.size(); ++i) r.batch[i] = static_cast<int32_t>(i);
    const RecordSet want = StablySorted(r);
    r.SortByVossel();
    ExpectSameRecords(r, want, what);
  };
  for (size_t tail : {1, 7, 300}) {
    RecordSet r = records(2000, true);
    r.Append(records(tail, false));
    check(r, "appended " + std::to_string(tail));
  }
  {
    RecordSet r = records(200, false);
    r.Append(records(2000, true));
    r.Append(records(300, false));
    check(r, "a sorted run inside");
  }
  check(records(2000, true), "in order");
  check(records(2000, false), "shuffled");
  check(records(1, false), "one");
  check(records(0, false), "none");
}

// Claim (records.h): MergeRenumbered is Select of the kept rows, their vossels renumbered, then
// Append of the added records and a stable SortByVossel, record for record; with a renumbering
// that keeps the vossels' order (an ingest's) and one that does not.
TEST(RecordSetTest, MergeRenumberedIsSelectAppendAndStableSort) {
  std::mt19937_64 rng(9);
  for (bool monotonic : {true, false}) {
    // The last sizes span many of the merge's parallel runs (32 768 places each).
    for (auto [kept_n, added_n] : {std::pair<size_t, size_t>{3000, 400}, {3000, 0}, {0, 500},
                                   {1, 1}, {0, 0}, {200000, 30000}, {150000, 150000}}) {
      RecordSet kept = KeyedRecords(rng, kept_n, true);
      RecordSet added = KeyedRecords(rng, added_n, false);
      for (size_t i = 0; i < kept.size(); ++i) kept.batch[i] = static_cast<int32_t>(i);
      for (size_t i = 0; i < added.size(); ++i) added.batch[i] = static_cast<int32_t>(100000 + i);
      // Vossels 0..40 renumbered into 0..90: spread out (vossels appeared between them), or
      // reversed.
      std::vector<int32_t> renumber(41);
      for (int32_t v = 0; v < 41; ++v) renumber[size_t(v)] = monotonic ? 2 * v + v % 3 : 90 - 2 * v;
      for (int32_t& v : added.vossel) v = 2 * v;  // the added ones are numbered in the new order
      std::vector<size_t> rows;
      for (size_t i = 0; i < kept.size(); ++i) {
        if (rng() % 4 != 0) rows.push_back(i);  // a quarter dropped (revisited, vanished)
      }
      RecordSet want = kept.Select(rows);
      for (int32_t& v : want.vossel) v = renumber[size_t(v)];
      want.Append(added);
      want = StablySorted(want);
      const RecordSet got = MergeRenumbered(kept, rows, renumber, added);
      ExpectSameRecords(got, want,
                        absl::StrCat(monotonic ? "monotonic" : "reversed", " renumbering, ",
                                     rows.size(), " kept and ", added.size(), " added"));
    }
  }
}

// Claim (records.h "Vossel order"): indices run over leaves in tree order, then voxel offset;
// the returned map is a permutation and every per-vossel array moves with its vossel.
TEST(CanonicalizeVosselOrderTest, IndicesFollowLeafThenOffsetOrder) {
  VosselGeometry g = RandomGeometry(20000, 11);
  const std::vector<openvdb::Coord> old_coord = g.coord;
  const std::vector<Eigen::Vector3f> old_centroid = g.centroid_m;
  const std::vector<int32_t> map = CanonicalizeVosselOrder(g);
  ASSERT_EQ(map.size(), old_coord.size());
  ASSERT_TRUE(g.index_grid);
  EXPECT_EQ(g.index_grid->getName(), "index");
  EXPECT_EQ(g.index_grid->background(), -1);
  EXPECT_NEAR(g.index_grid->transform().voxelSize()[0], 0.02, 1e-12);

  std::vector<int32_t> sorted = map;
  std::sort(sorted.begin(), sorted.end());
  std::vector<int32_t> iota(map.size());
  std::iota(iota.begin(), iota.end(), 0);
  EXPECT_EQ(sorted, iota) << "old->new map is not a permutation";

  int32_t expect = 0;
  size_t leaves = 0;
  for (auto leaf = g.index_grid->tree().cbeginLeaf(); leaf; ++leaf, ++leaves) {
    for (auto it = leaf->cbeginValueOn(); it; ++it, ++expect) {
      ASSERT_EQ(*it, expect) << "vossel at " << it.getCoord() << " out of leaf/offset order";
      ASSERT_EQ(g.coord[expect], it.getCoord());
    }
  }
  EXPECT_EQ(static_cast<size_t>(expect), old_coord.size());
  size_t moved_wrong = 0;
  for (size_t i = 0; i < map.size(); ++i) {
    moved_wrong += g.coord[map[i]] != old_coord[i];
    moved_wrong += g.point_count[map[i]] != static_cast<int32_t>(i);
    moved_wrong += g.centroid_m[map[i]] != old_centroid[i];
  }
  EXPECT_EQ(moved_wrong, 0u);
  std::printf("canonical order: %zu vossels in %zu leaves, %zu inconsistent moves\n", map.size(),
              leaves, moved_wrong);
}

// Claim: an empty array stays empty and the index grid of no vossels is valid.
TEST(CanonicalizeVosselOrderTest, EmptyArraysStayEmpty) {
  VosselGeometry g;
  g.coord = {openvdb::Coord(3, 2, 1), openvdb::Coord(-9, 0, 0), openvdb::Coord(0, 0, 0)};
  const std::vector<int32_t> map = CanonicalizeVosselOrder(g);
  EXPECT_EQ(map.size(), 3u);
  EXPECT_TRUE(g.point_count.empty());
  EXPECT_TRUE(g.normal.empty());
  EXPECT_EQ(g.index_grid->activeVoxelCount(), 3u);
  VosselGeometry none;
  EXPECT_TRUE(CanonicalizeVosselOrder(none).empty());
  EXPECT_EQ(none.index_grid->activeVoxelCount(), 0u);
}

// Claim (record_grid.h InsertVossels): inserting vossels into a canonical geometry gives what
// CanonicalizeVosselOrder gives of its arrays with the new vossels appended (zero sums, counts,
// centroid, normal, covariance, default frame), bit for bit, with each vossel's index in it:
// with every array present, with sums and frames absent (filled as resizing would), from a
// geometry without an index grid, and into an empty one.
TEST(InsertVosselsTest, IsCanonicalizeOfTheAppendedVossels) {
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::uniform_int_distribution<int> c(-60, 59);
  for (const char* variant : {"full", "no sums or frames", "no index grid", "empty"}) {
    SCOPED_TRACE(variant);
    const std::string v = variant;
    VosselGeometry base = v == "empty" ? VosselGeometry{} : RandomGeometry(20000, 11);
    if (v == "full") {
      for (size_t i = 0; i < base.size(); ++i) {
        VosselSums sums;
        sums.sum_m = {u(rng), u(rng), u(rng)};
        sums.sum_xx_m2 = {u(rng), u(rng), u(rng), u(rng), u(rng), u(rng)};
        sums.view_sum = {u(rng), u(rng), u(rng)};
        base.sums.push_back(sums);
        VosselFrame f;
        f.count = int32_t(i % 7);
        f.centroid_m = Eigen::Vector3d(u(rng), u(rng), u(rng)).cast<float>();
        f.normal = Eigen::Vector3d(u(rng), u(rng), u(rng)).cast<float>();
        base.frame.push_back(f);
      }
    }
    CanonicalizeVosselOrder(base);
    // Half of the added coordinates are base's vossels, half new (some twice), shuffled.
    std::vector<openvdb::Coord> added;
    std::set<openvdb::Coord> in_base(base.coord.begin(), base.coord.end()), made;
    for (size_t i = 0; i < base.size(); i += 8) added.push_back(base.coord[i]);
    while (made.size() < 3000) {
      const openvdb::Coord k(c(rng), c(rng), c(rng));
      if (!in_base.count(k) && made.insert(k).second) added.push_back(k);
    }
    for (size_t i = 0; i < 200; ++i) added.push_back(added[added.size() - 1 - 2 * i]);
    std::shuffle(added.begin(), added.end(), rng);

    VosselGeometry expect = base;
    std::set<openvdb::Coord> appended;
    for (const openvdb::Coord& k : added) {
      if (in_base.count(k) || !appended.insert(k).second) continue;
      expect.coord.push_back(k);
    }
    expect.point_count.resize(expect.coord.size(), 0);
    expect.centroid_m.resize(expect.coord.size(), Eigen::Vector3f::Zero());
    expect.normal.resize(expect.coord.size(), Eigen::Vector3f::Zero());
    expect.covariance_m2.resize(expect.coord.size(), {0, 0, 0, 0, 0, 0});
    expect.sums.resize(base.size());
    expect.sums.resize(expect.coord.size());
    expect.frame.resize(base.size());
    expect.frame.resize(expect.coord.size());
    const std::vector<int32_t> map = CanonicalizeVosselOrder(expect);

    if (v == "no index grid") base.index_grid.reset();
    if (v == "empty") base.index_grid.reset();
    VosselGeometry got;
    const VosselInsertion ins = InsertVossels(base, added, &got);
    ASSERT_EQ(got.size(), expect.size());
    EXPECT_EQ(got.coord, expect.coord);
    EXPECT_EQ(got.point_count, expect.point_count);
    EXPECT_EQ(got.centroid_m, expect.centroid_m);
    EXPECT_EQ(got.normal, expect.normal);
    EXPECT_EQ(got.covariance_m2, expect.covariance_m2);
    EXPECT_TRUE(got.sums == expect.sums);
    EXPECT_TRUE(got.frame == expect.frame);
    EXPECT_EQ(got.vossel_size_m, base.vossel_size_m);
    EXPECT_EQ(ins.old_to_new, std::vector<int32_t>(map.begin(), map.begin() + base.size()));
    ASSERT_EQ(ins.added_to_new.size(), added.size());
    size_t wrong = 0, created = 0;
    std::set<openvdb::Coord> seen;
    for (size_t i = 0; i < added.size(); ++i) {
      wrong += got.coord[size_t(ins.added_to_new[i])] != added[i];
      const bool first_new = !in_base.count(added[i]) && seen.insert(added[i]).second;
      wrong += bool(ins.created[i]) != first_new;
      created += ins.created[i];
    }
    EXPECT_EQ(wrong, 0u);
    EXPECT_EQ(created, expect.size() - base.size());
    ASSERT_TRUE(got.index_grid);
    EXPECT_EQ(got.index_grid->activeVoxelCount(), expect.index_grid->activeVoxelCount());
    int32_t at = 0;
    for (auto it = got.index_grid->tree().cbeginValueOn(); it; ++it) {
      wrong += *it != expect.index_grid->tree().getValue(it.getCoord());
      ++at;
    }
    EXPECT_EQ(wrong, 0u);
    EXPECT_EQ(size_t(at), expect.size());
    EXPECT_EQ(got.index_grid->transform(), expect.index_grid->transform());
    std::printf("%s: %zu vossels + %zu added coordinates -> %zu vossels, %zu made\n", variant,
                base.size(), added.size(), got.size(), created);
  }
}

// Claim (§6): records.vdb reproduces every record within its codec's precision:
//   scan, modality, flags, batch, range: exact; value, foot: half, |Δ| ≤ 2⁻¹¹·|x| + 6e-8;
//   cos_inc: 16-bit unit range, |Δ| ≤ 0.5/65535; uv: 16-bit fractions of 16384 px,
//   |Δ| ≤ 0.5·16384/65535 px = 0.125 px; vis, conf: 8-bit unit range, |Δ| ≤ 0.5/255,
//   and vis = 0.5 reads back ≥ 0.5 (RECORDS-NOTES pitfall 6).
TEST(RecordGridTest, RoundTripWithinCodecPrecision) {
  const fs::path dir = TestDir("roundtrip");
  VosselGeometry g = RandomGeometry(20000, 5);
  CanonicalizeVosselOrder(g);
  const RecordSet in = RandomRecords(g.size(), 6);
  const fs::path path = dir / "records.vdb";
  ASSERT_TRUE(WriteRecords(g, in, path).ok());
  absl::StatusOr<RecordSet> out = ReadRecords(g, path);
  ASSERT_TRUE(out.ok()) << out.status();
  ASSERT_EQ(out->size(), in.size());

  EXPECT_EQ(out->vossel, in.vossel);
  EXPECT_EQ(out->scan, in.scan);
  EXPECT_EQ(out->modality, in.modality);
  EXPECT_EQ(out->flags, in.flags);
  EXPECT_EQ(out->batch, in.batch);
  auto rel = [](float x) { return std::fabs(double(x)) + 6e-8 * 2048.0; };
  auto abs1 = [](float) { return 1.0; };
  const double value_rel = WorstError(in.value, out->value, rel);
  const double range_rel = WorstError(in.range_m, out->range_m, rel);
  const double major_rel = WorstError(in.foot_major_m, out->foot_major_m, rel);
  const double minor_rel = WorstError(in.foot_minor_m, out->foot_minor_m, rel);
  const double cos_abs = WorstError(in.cos_inc, out->cos_inc, abs1);
  const double vis_abs = WorstError(in.vis, out->vis, abs1);
  const double conf_abs = WorstError(in.conf, out->conf, abs1);
  const double uv_px = WorstError(in.uv_px, out->uv_px, abs1);
  EXPECT_LE(uv_px, 0.5 * 16384.0 / 65535.0 + 1e-3);
  std::printf("  worst uv error %.4f px (bound 0.125)\n", uv_px);
  const double half_rel = std::ldexp(1.0, -11);
  EXPECT_LE(value_rel, half_rel);
  EXPECT_EQ(range_rel, 0.0) << "range is stored as float";
  EXPECT_LE(major_rel, half_rel);
  EXPECT_LE(minor_rel, half_rel);
  EXPECT_LE(cos_abs, 0.5 / 65535 + 1e-7);
  EXPECT_LE(vis_abs, 0.5 / 255 + 1e-7);
  EXPECT_LE(conf_abs, 0.5 / 255 + 1e-7);
  size_t half_vis = 0, flipped = 0;
  for (size_t i = 0; i < in.size(); ++i) {
    if (in.vis[i] == 0.5f) {
      ++half_vis;
      flipped += out->vis[i] < 0.5f;
    }
  }
  EXPECT_GT(half_vis, 0u);
  EXPECT_EQ(flipped, 0u) << "vis = 0.5 read back below 0.5";

  const double bytes = static_cast<double>(fs::file_size(path));
  std::printf(
      "records round trip: %zu vossels, %zu records, %.1f B/record on disk (blosc)\n"
      "  worst relative error: value %.3g, range %.3g, foot_major %.3g, foot_minor %.3g "
      "(half bound %.3g)\n"
      "  worst absolute error: cos_inc %.3g (bound %.3g), vis %.3g, conf %.3g (bound %.3g)\n"
      "  vis = 0.5: %zu records, %zu read back below 0.5\n",
      g.size(), in.size(), bytes / in.size(), value_rel, range_rel, major_rel, minor_rel,
      half_rel, cos_abs, 0.5 / 65535, vis_abs, conf_abs, 0.5 / 255, half_vis, flipped);

  // Offsets valid and one point per record, read with OpenVDB directly.
  openvdb::io::File file(path.string());
  file.open(false);
  auto grid = openvdb::GridBase::grid<openvdb::points::PointDataGrid>(file.readGrid("records"));
  file.close();
  ASSERT_TRUE(grid);
  size_t points = 0;
  for (auto leaf = grid->tree().cbeginLeaf(); leaf; ++leaf) {
    EXPECT_NO_THROW(leaf->validateOffsets());
    points += leaf->pointCount();
    EXPECT_TRUE(leaf->constAttributeArray("P").isUniform()) << "position must stay uniform";
  }
  EXPECT_EQ(points, in.size());

  // vdb_print opens the file (only registered types, pitfall 1).
  const std::string cmd = "/usr/bin/vdb_print -l " + path.string() + " > /dev/null 2>&1";
  const int rc = std::system(cmd.c_str());
  std::printf("vdb_print -l %s: exit status %d\n", path.filename().c_str(), rc);
  EXPECT_EQ(rc, 0);
  fs::remove_all(dir);
}

// Claim: ListRecordAttributes reports every §6 attribute with its type, codec and stride.
TEST(RecordGridTest, ListsAttributesWithTypeCodecStride) {
  const fs::path dir = TestDir("list");
  VosselGeometry g = RandomGeometry(500, 8);
  CanonicalizeVosselOrder(g);
  const RecordSet in = RandomRecords(g.size(), 9);
  ASSERT_TRUE(WriteRecords(g, in, dir / "records.vdb").ok());
  absl::StatusOr<std::vector<AttributeInfo>> list = ListRecordAttributes(dir / "records.vdb");
  ASSERT_TRUE(list.ok()) << list.status();
  std::map<std::string, AttributeInfo> by_name;
  for (const AttributeInfo& a : *list) {
    std::printf("  %-10s %-6s %-8s stride %d\n", a.name.c_str(), a.type.c_str(),
                a.codec.c_str(), a.stride);
    by_name[a.name] = a;
  }
  const std::vector<std::tuple<std::string, std::string, std::string, int>> expect = {
      {"P", "vec3s", "null", 1},         {"scan", "int16", "null", 1},
      {"modality", "int8", "null", 1},   {"value", "float", "trnc", 3},
      {"range", "float", "null", 1},     {"cos_inc", "float", "ufxpt16", 1},
      {"foot_major", "float", "trnc", 1}, {"foot_minor", "float", "trnc", 1},
      {"uv", "float", "ufxpt16", 2},     {"vis", "float", "ufxpt8", 1},
      {"conf", "float", "ufxpt8", 6},    {"flags", "int8", "null", 1},
      {"batch", "int16", "null", 1}};
  EXPECT_EQ(list->size(), expect.size());
  for (const auto& [name, type, codec, stride] : expect) {
    ASSERT_TRUE(by_name.count(name)) << name;
    EXPECT_EQ(by_name[name].type, type) << name;
    EXPECT_EQ(by_name[name].codec, codec) << name;
    EXPECT_EQ(by_name[name].stride, stride) << name;
  }

  // No records at all: the list comes from the grid metadata.
  ASSERT_TRUE(WriteRecords(g, RecordSet(), dir / "empty.vdb").ok());
  absl::StatusOr<std::vector<AttributeInfo>> empty = ListRecordAttributes(dir / "empty.vdb");
  ASSERT_TRUE(empty.ok()) << empty.status();
  EXPECT_EQ(empty->size(), expect.size());
  absl::StatusOr<RecordSet> none = ReadRecords(g, dir / "empty.vdb");
  ASSERT_TRUE(none.ok()) << none.status();
  EXPECT_EQ(none->size(), 0u);
  fs::remove_all(dir);
}

// Claim (§9): a file written when a record had four confidence factors (conf of stride 4) reads
// with those four as stored and the factors added since (smear, fog) at 1; any other stride
// mismatch is still an error.
TEST(RecordGridTest, ReadsOlderNarrowerConfidence) {
  const fs::path dir = TestDir("narrow-conf");
  VosselGeometry g = RandomGeometry(3000, 21);
  CanonicalizeVosselOrder(g);
  const fs::path path = dir / "records.vdb";
  ASSERT_TRUE(WriteRecords(g, RandomRecords(g.size(), 22), path).ok());
  absl::StatusOr<RecordSet> wide = ReadRecords(g, path);
  ASSERT_TRUE(wide.ok()) << wide.status();
  ASSERT_EQ(kConfidenceCount, 6);
  // Rewrite the file's conf as the four-factor layout held it, in the reader's record order.
  auto rewrite_conf = [&](int stride) {
    openvdb::io::File file(path.string());
    file.open(false);
    openvdb::GridPtrVecPtr grids = file.getGrids();
    openvdb::MetaMap::Ptr meta = file.getMetadata();
    file.close();
    for (openvdb::GridBase::Ptr& base : *grids) {
      auto grid = openvdb::gridPtrCast<openvdb::points::PointDataGrid>(base);
      if (!grid || grid->getName() != "records") continue;
      openvdb::points::dropAttribute(grid->tree(), "conf");
      using Unit8 = openvdb::points::FixedPointCodec<true, openvdb::points::UnitRange>;
      openvdb::points::appendAttribute<float, Unit8>(grid->tree(), "conf", 1.0f,
                                                     openvdb::Index(stride),
                                                     /*constantStride=*/true, nullptr, false,
                                                     false);
      size_t k = 0;
      for (auto leaf = grid->tree().beginLeaf(); leaf; ++leaf) {
        auto& array = leaf->attributeArray("conf");
        openvdb::points::AttributeWriteHandle<float> handle(array);
        for (openvdb::Index n = 0; n < leaf->pointCount(); ++n, ++k) {
          for (int c = 0; c < stride; ++c) {
            handle.set(n, openvdb::Index(c), wide->conf[k * kConfidenceCount + size_t(c)]);
          }
        }
      }
    }
    openvdb::io::File out(path.string());
    out.write(*grids, *meta);
  };
  rewrite_conf(4);
  absl::StatusOr<RecordSet> narrow = ReadRecords(g, path);
  ASSERT_TRUE(narrow.ok()) << narrow.status();
  ASSERT_EQ(narrow->size(), wide->size());
  int64_t kept = 0, ones = 0;
  for (size_t i = 0; i < narrow->size(); ++i) {
    for (int c = 0; c < kConfidenceCount; ++c) {
      const float got = narrow->conf[i * kConfidenceCount + size_t(c)];
      if (c < 4) kept += got == wide->conf[i * kConfidenceCount + size_t(c)];
      else ones += got == 1.0f;
    }
  }
  EXPECT_EQ(kept, int64_t(4 * narrow->size()));
  EXPECT_EQ(ones, int64_t(2 * narrow->size()));
  EXPECT_EQ(narrow->value, wide->value);
  rewrite_conf(7);  // wider than any layout this build knows: refused, not misread
  EXPECT_EQ(ReadRecords(g, path).status().code(), absl::StatusCode::kDataLoss);
  fs::remove_all(dir);
}

// Claim: ids beyond int16 and radiometry beyond the half range (65504) are stored wider and
// read back exactly, instead of wrapping or becoming infinite.
TEST(RecordGridTest, WidensStorageOutsideNarrowRanges) {
  const fs::path dir = TestDir("widen");
  VosselGeometry g = RandomGeometry(200, 3);
  CanonicalizeVosselOrder(g);
  RecordSet in = RandomRecords(g.size(), 4);
  in.scan[0] = 70000;
  in.batch[1] = -40000;
  in.value[2] = 1.0e6f;
  ASSERT_TRUE(WriteRecords(g, in, dir / "records.vdb").ok());
  absl::StatusOr<RecordSet> out = ReadRecords(g, dir / "records.vdb");
  ASSERT_TRUE(out.ok()) << out.status();
  EXPECT_EQ(out->scan, in.scan);
  EXPECT_EQ(out->batch, in.batch);
  EXPECT_EQ(out->value, in.value);  // float storage: exact
  absl::StatusOr<std::vector<AttributeInfo>> list = ListRecordAttributes(dir / "records.vdb");
  ASSERT_TRUE(list.ok());
  for (const AttributeInfo& a : *list) {
    if (a.name == "scan" || a.name == "batch") {
      EXPECT_EQ(a.type, "int32");
    }
    if (a.name == "value") {
      EXPECT_EQ(a.codec, "null");
    }
  }
  fs::remove_all(dir);
}

// Claim: bad input is refused with INVALID_ARGUMENT and writes nothing; a missing file is
// NOT_FOUND.
TEST(RecordGridTest, RejectsBadInput) {
  const fs::path dir = TestDir("bad");
  VosselGeometry g = RandomGeometry(100, 1);
  CanonicalizeVosselOrder(g);
  RecordSet in = RandomRecords(g.size(), 2);
  std::swap(in.vossel.front(), in.vossel.back());
  EXPECT_EQ(WriteRecords(g, in, dir / "r.vdb").code(), absl::StatusCode::kInvalidArgument);
  in = RandomRecords(g.size(), 2);
  in.vossel.back() = static_cast<int32_t>(g.size());
  EXPECT_EQ(WriteRecords(g, in, dir / "r.vdb").code(), absl::StatusCode::kInvalidArgument);
  in = RandomRecords(g.size(), 2);
  in.conf.pop_back();
  EXPECT_EQ(WriteRecords(g, in, dir / "r.vdb").code(), absl::StatusCode::kInvalidArgument);
  EXPECT_FALSE(fs::exists(dir / "r.vdb"));
  EXPECT_EQ(ReadRecords(g, dir / "missing.vdb").status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(ReadGeometry(dir / "missing.vdb").status().code(), absl::StatusCode::kNotFound);
  // A non-canonical index grid is refused.
  VosselGeometry shuffled = g;
  shuffled.index_grid = g.index_grid->deepCopy();
  shuffled.index_grid->tree().setValue(g.coord[0], 7);
  EXPECT_EQ(WriteGeometry(shuffled, dir / "g.vdb").code(),
            absl::StatusCode::kFailedPrecondition);
  fs::remove_all(dir);
}

// Claim (record_grid.h): geometry.vdb restores the lattice, the canonical order and every
// per-vossel array exactly (float grids, no quantisation).
TEST(GeometryGridTest, RoundTripExact) {
  const fs::path dir = TestDir("geometry");
  VosselGeometry g = RandomGeometry(20000, 21);
  g.vossel_size_m = 0.05;
  CanonicalizeVosselOrder(g);
  ASSERT_TRUE(WriteGeometry(g, dir / "geometry.vdb").ok());
  absl::StatusOr<VosselGeometry> back = ReadGeometry(dir / "geometry.vdb");
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_NEAR(back->vossel_size_m, 0.05, 1e-12);
  EXPECT_EQ(back->coord, g.coord);
  EXPECT_EQ(back->point_count, g.point_count);
  EXPECT_EQ(back->centroid_m, g.centroid_m);
  EXPECT_EQ(back->normal, g.normal);
  EXPECT_EQ(back->covariance_m2, g.covariance_m2);
  EXPECT_EQ(back->index_grid->activeVoxelCount(), g.size());
  std::printf("geometry round trip: %zu vossels, %.1f B/vossel on disk\n", g.size(),
              double(fs::file_size(dir / "geometry.vdb")) / g.size());
  const std::string cmd = "/usr/bin/vdb_print " + (dir / "geometry.vdb").string() + " > /dev/null";
  EXPECT_EQ(std::system(cmd.c_str()), 0);

  // The lattice alone (a reweight's read): the same index and coordinates, no other array, and
  // records written against the whole geometry read back against it.
  absl::StatusOr<VosselGeometry> lattice = ReadLattice(dir / "geometry.vdb");
  ASSERT_TRUE(lattice.ok()) << lattice.status();
  EXPECT_NEAR(lattice->vossel_size_m, 0.05, 1e-12);
  EXPECT_EQ(lattice->coord, g.coord);
  EXPECT_TRUE(lattice->point_count.empty() && lattice->centroid_m.empty() &&
              lattice->sums.empty() && lattice->frame.empty());
  const RecordSet recs = RandomRecords(g.size(), 3);
  ASSERT_TRUE(WriteRecords(g, recs, dir / "records.vdb").ok());
  absl::StatusOr<RecordSet> via_lattice = ReadRecords(*lattice, dir / "records.vdb");
  absl::StatusOr<RecordSet> via_geometry = ReadRecords(*back, dir / "records.vdb");
  ASSERT_TRUE(via_lattice.ok() && via_geometry.ok());
  EXPECT_EQ(via_lattice->vossel, via_geometry->vossel);
  EXPECT_EQ(via_lattice->value, via_geometry->value);
  EXPECT_EQ(ReadLattice(dir / "missing.vdb").status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(ReadLattice(dir / "records.vdb").status().code(), absl::StatusCode::kDataLoss);

  // Arrays left empty stay empty.
  VosselGeometry bare;
  bare.coord = g.coord;
  CanonicalizeVosselOrder(bare);
  ASSERT_TRUE(WriteGeometry(bare, dir / "bare.vdb").ok());
  absl::StatusOr<VosselGeometry> bare_back = ReadGeometry(dir / "bare.vdb");
  ASSERT_TRUE(bare_back.ok());
  EXPECT_EQ(bare_back->coord, g.coord);
  EXPECT_TRUE(bare_back->point_count.empty());
  EXPECT_TRUE(bare_back->covariance_m2.empty());
  fs::remove_all(dir);
}

/// Writes `bytes` to `path`.
void WriteBytes(const fs::path& path, const std::string& bytes) {
  std::FILE* f = std::fopen(path.c_str(), "wb");
  ASSERT_NE(f, nullptr);
  ASSERT_EQ(std::fwrite(bytes.data(), 1, bytes.size(), f), bytes.size());
  std::fclose(f);
}

/// The names of the grids in the .vdb file `path`.
std::set<std::string> GridNames(const fs::path& path) {
  std::set<std::string> names;
  openvdb::io::File file(path.string());
  file.open();
  for (auto it = file.beginName(); it != file.endName(); ++it) names.insert(*it);
  file.close();
  return names;
}

/// Every array of `back` equals `g`'s, bit for bit.
void ExpectSameGeometry(const VosselGeometry& back, const VosselGeometry& g) {
  EXPECT_EQ(back.coord, g.coord);
  EXPECT_EQ(back.point_count, g.point_count);
  EXPECT_EQ(back.centroid_m, g.centroid_m);
  EXPECT_EQ(back.covariance_m2, g.covariance_m2);
  EXPECT_EQ(back.normal, g.normal);
  ASSERT_EQ(back.sums.size(), g.sums.size());
  for (size_t v = 0; v < g.sums.size(); ++v) ASSERT_TRUE(back.sums[v] == g.sums[v]) << v;
  ASSERT_EQ(back.frame.size(), g.frame.size());
  for (size_t v = 0; v < g.frame.size(); ++v) ASSERT_TRUE(back.frame[v] == g.frame[v]) << v;
}

// Claim (§1 on disk): a geometry object (EncodeGeometry) keeps the exact sums and not the
// centroid and covariance they give; read back, those are derived again (FrameOf) to the same
// bits an ingest derived before writing it. Its arrays are the attributes of one point per
// vossel ("vossels"), beside the "index" grid; the file a user opens (WriteGeometry) keeps a
// plain grid per array, centroid and covariance too. Objects of the older layout (plain grids
// without centroid and covariance) still read to the same geometry.
TEST(GeometryGridTest, ObjectsKeepTheSumsAndDeriveWhatTheyGive) {
  const fs::path dir = TestDir("geometry-object");
  VosselGeometry g = RandomGeometry(20000, 23);
  g.vossel_size_m = 0.05;
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<double> u(-0.025, 0.025);
  g.sums.resize(g.size());
  g.frame.resize(g.size());
  for (size_t v = 0; v < g.size(); ++v) {
    const int32_t n = 1 + g.point_count[v] % 40;
    g.point_count[v] = n;
    for (int p = 0; p < n; ++p) {  // points in the vossel, relative to its centre
      const Eigen::Vector3d x(u(rng), u(rng), u(rng));
      g.sums[v].sum_m += x;
      const double xx[6] = {x.x() * x.x(), x.x() * x.y(), x.x() * x.z(),
                            x.y() * x.y(), x.y() * x.z(), x.z() * x.z()};
      for (int i = 0; i < 6; ++i) g.sums[v].sum_xx_m2[i] += xx[i];
      g.sums[v].view_sum += Eigen::Vector3d(u(rng), u(rng), 1.0).normalized();
    }
    const VosselFrame all = FrameOf(g.coord[v], n, g.sums[v], g.vossel_size_m);
    g.centroid_m[v] = all.centroid_m;
    g.covariance_m2[v] = all.covariance_m2;
    g.frame[v] = FrameOf(g.coord[v], n / 2 + 1, g.sums[v], g.vossel_size_m);  // another LiDAR's
    g.frame[v].normal = g.normal[(v + 1) % g.size()];
  }
  CanonicalizeVosselOrder(g);
  absl::StatusOr<std::string> bytes = EncodeGeometry(g);
  ASSERT_TRUE(bytes.ok()) << bytes.status();
  const fs::path object = dir / "object.vdb";
  WriteBytes(object, *bytes);
  ASSERT_TRUE(WriteGeometry(g, dir / "file.vdb").ok());
  EXPECT_EQ(GridNames(object), (std::set<std::string>{"index", "vossels"}));
  {
    openvdb::io::File file(object.string());
    file.open();
    auto points = openvdb::gridPtrCast<openvdb::points::PointDataGrid>(file.readGrid("vossels"));
    file.close();
    ASSERT_TRUE(points);
    EXPECT_EQ(openvdb::points::pointCount(points->tree()), g.size());  // a point per vossel
    const auto& descriptor = points->tree().cbeginLeaf()->attributeSet().descriptor();
    for (const char* name : {"count", "normal", "sum", "sum_xx", "view_sum", "frame_count",
                             "frame_centroid", "frame_covariance", "frame_view", "frame_normal"}) {
      EXPECT_NE(descriptor.find(name), openvdb::points::AttributeSet::INVALID_POS) << name;
    }
    for (const char* name : {"centroid", "covariance"}) {
      EXPECT_EQ(descriptor.find(name), openvdb::points::AttributeSet::INVALID_POS) << name;
    }
  }
  const std::set<std::string> in_file = GridNames(dir / "file.vdb");
  for (const char* name : {"centroid", "covariance_diag", "covariance_off", "sum", "normal"}) {
    EXPECT_EQ(in_file.count(name), 1u) << name;
  }
  const double object_b = double(bytes->size()) / g.size();
  const double file_b = double(fs::file_size(dir / "file.vdb")) / g.size();
  std::printf("geometry object %.1f B/vossel, file with centroid and covariance %.1f B/vossel\n",
              object_b, file_b);
  EXPECT_LT(object_b, file_b - 30.0);  // 36 bytes of values a vossel, less the leaves' masks

  absl::StatusOr<VosselGeometry> back = ReadGeometry(object);
  ASSERT_TRUE(back.ok()) << back.status();
  ExpectSameGeometry(*back, g);
  // A file with the grids reads them as stored.
  absl::StatusOr<VosselGeometry> file_back = ReadGeometry(dir / "file.vdb");
  ASSERT_TRUE(file_back.ok());
  ExpectSameGeometry(*file_back, g);

  // The older layout of an object: the plain grids, without centroid and covariance.
  absl::StatusOr<openvdb::GridCPtrVec> grids = GeometryGrids(g, "old object");
  ASSERT_TRUE(grids.ok()) << grids.status();
  openvdb::GridCPtrVec stored;
  for (const openvdb::GridBase::ConstPtr& grid : *grids) {
    if (grid->getName() != "centroid" && grid->getName().rfind("covariance", 0) != 0) {
      stored.push_back(grid);
    }
  }
  ASSERT_EQ(stored.size(), grids->size() - 3);
  absl::StatusOr<std::string> old_bytes = internal::EncodeVdbFile(
      stored, openvdb::MetaMap(), internal::VdbCompression::kActiveMaskOnly, "old object");
  ASSERT_TRUE(old_bytes.ok()) << old_bytes.status();
  WriteBytes(dir / "old.vdb", *old_bytes);
  absl::StatusOr<VosselGeometry> old_back = ReadGeometry(dir / "old.vdb");
  ASSERT_TRUE(old_back.ok()) << old_back.status();
  ExpectSameGeometry(*old_back, g);
  fs::remove_all(dir);
}

// Claim: a geometry built without the sums (by hand, or read from a store written before
// them) keeps its centroid and covariance in its object, and one without frames or counts
// keeps what it has: each reads back as it was written.
TEST(GeometryGridTest, ObjectsWithoutSumsKeepTheirSurface) {
  const fs::path dir = TestDir("geometry-object-bare");
  VosselGeometry g = RandomGeometry(5000, 29);
  CanonicalizeVosselOrder(g);
  VosselGeometry lattice_only;
  lattice_only.coord = g.coord;
  CanonicalizeVosselOrder(lattice_only);
  for (const VosselGeometry* geometry : {&g, &lattice_only}) {
    absl::StatusOr<std::string> bytes = EncodeGeometry(*geometry);
    ASSERT_TRUE(bytes.ok()) << bytes.status();
    WriteBytes(dir / "object.vdb", *bytes);
    absl::StatusOr<VosselGeometry> back = ReadGeometry(dir / "object.vdb");
    ASSERT_TRUE(back.ok()) << back.status();
    ExpectSameGeometry(*back, *geometry);
  }
  fs::remove_all(dir);
}

// Claim: a geometry object whose vossel points do not match its index grid, or lack part of a
// group of attributes, is refused as DATA_LOSS rather than read into wrong vossels.
TEST(GeometryGridTest, MismatchedVosselPointsAreDataLoss) {
  const fs::path dir = TestDir("geometry-object-bad");
  VosselGeometry g = RandomGeometry(3000, 31);
  CanonicalizeVosselOrder(g);
  VosselGeometry other = RandomGeometry(3000, 37);
  CanonicalizeVosselOrder(other);
  absl::StatusOr<std::string> a = EncodeGeometry(g), b = EncodeGeometry(other);
  ASSERT_TRUE(a.ok() && b.ok());
  WriteBytes(dir / "a.vdb", *a);
  WriteBytes(dir / "b.vdb", *b);
  // g's index grid beside other's vossel points.
  openvdb::GridPtrVecPtr grids_a, grids_b;
  for (auto [path, grids] :
       {std::pair{dir / "a.vdb", &grids_a}, std::pair{dir / "b.vdb", &grids_b}}) {
    openvdb::io::File file(path.string());
    file.open();
    *grids = file.getGrids();
    file.close();
  }
  openvdb::GridCPtrVec mixed;
  for (const auto& grid : *grids_a) {
    if (grid->getName() == "index") mixed.push_back(grid);
  }
  for (const auto& grid : *grids_b) {
    if (grid->getName() == "vossels") mixed.push_back(grid);
  }
  ASSERT_EQ(mixed.size(), 2u);
  absl::StatusOr<std::string> bad = internal::EncodeVdbFile(
      mixed, openvdb::MetaMap(), internal::VdbCompression::kActiveMaskOnly, "mixed");
  ASSERT_TRUE(bad.ok());
  WriteBytes(dir / "mixed.vdb", *bad);
  absl::StatusOr<VosselGeometry> back = ReadGeometry(dir / "mixed.vdb");
  ASSERT_FALSE(back.ok());
  EXPECT_EQ(back.status().code(), absl::StatusCode::kDataLoss) << back.status();

  // A sums group with one of its attributes dropped.
  VosselGeometry with_sums = g;
  with_sums.sums.resize(with_sums.size());
  absl::StatusOr<std::string> full = EncodeGeometry(with_sums);
  ASSERT_TRUE(full.ok());
  WriteBytes(dir / "full.vdb", *full);
  openvdb::GridPtrVecPtr grids;
  {
    openvdb::io::File file((dir / "full.vdb").string());
    file.open();
    grids = file.getGrids();
    file.close();
  }
  for (const auto& grid : *grids) {
    if (auto points = openvdb::gridPtrCast<openvdb::points::PointDataGrid>(grid)) {
      openvdb::points::dropAttribute(points->tree(), "sum_xx");
    }
  }
  absl::StatusOr<std::string> partial = internal::EncodeVdbFile(
      openvdb::GridCPtrVec(grids->begin(), grids->end()), openvdb::MetaMap(),
      internal::VdbCompression::kActiveMaskOnly, "partial");
  ASSERT_TRUE(partial.ok());
  WriteBytes(dir / "partial.vdb", *partial);
  back = ReadGeometry(dir / "partial.vdb");
  ASSERT_FALSE(back.ok());
  EXPECT_EQ(back.status().code(), absl::StatusCode::kDataLoss) << back.status();
  EXPECT_NE(back.status().message().find("sum"), std::string::npos) << back.status();
  fs::remove_all(dir);
}

// Claim (§7 on disk): fused values round-trip exactly where weight > 0 and read back as zeros
// elsewhere; only weighted vossels are active; the profile name survives.
TEST(FusedGridTest, RoundTripWeightedVossels) {
  const fs::path dir = TestDir("fused");
  VosselGeometry g = RandomGeometry(20000, 31);
  CanonicalizeVosselOrder(g);
  const size_t n = g.size();
  std::mt19937_64 rng(32);
  std::uniform_real_distribution<float> u(0.0f, 3.0f);
  FusedValues f;
  f.profile = "default";
  for (Modality m : {Modality::kRgb, Modality::kLidar}) {
    FusedModality& fm = f.by_modality[m];
    fm.channels = ChannelCount(m);
    for (size_t v = 0; v < n; ++v) {
      const bool weighted = (v % 3) != 0;
      for (int c = 0; c < fm.channels; ++c) fm.value.push_back(weighted ? u(rng) : 0.0f);
      fm.weight.push_back(weighted ? u(rng) + 0.01f : 0.0f);
      fm.uncertainty.push_back(weighted ? u(rng) : 0.0f);
    }
  }
  ASSERT_TRUE(WriteFused(g, f, dir / "fused-default.vdb").ok());
  absl::StatusOr<FusedValues> back = ReadFused(g, dir / "fused-default.vdb");
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->profile, "default");
  ASSERT_EQ(back->by_modality.size(), 2u);
  for (const auto& [m, fm] : f.by_modality) {
    const FusedModality& b = back->by_modality.at(m);
    EXPECT_EQ(b.channels, fm.channels);
    EXPECT_EQ(b.value, fm.value);
    EXPECT_EQ(b.weight, fm.weight);
    EXPECT_EQ(b.uncertainty, fm.uncertainty);
  }
  openvdb::io::File file((dir / "fused-default.vdb").string());
  file.open();
  const auto weight = file.readGrid("rgb.weight");
  file.close();
  const size_t expect_active = n - (n + 2) / 3;
  EXPECT_EQ(weight->activeVoxelCount(), expect_active);
  std::printf("fused round trip: %zu vossels, %zu active (weight > 0), %.1f B/vossel on disk\n",
              n, size_t(weight->activeVoxelCount()),
              double(fs::file_size(dir / "fused-default.vdb")) / n);
  fs::remove_all(dir);
}

// Claim (§7 on disk): a fused object (EncodeFused) reads back as the fused file does: values
// exactly where weight > 0 and zeros elsewhere (a value left where the weight is 0 or NaN is
// not kept). It holds one PointDataGrid, "fused", a point per vossel with "<modality>_value",
// "_weight" and "_uncertainty"; objects of the older layout (the plain grids of the file) still
// read; a modality without its weight is DATA_LOSS.
TEST(FusedGridTest, ObjectsReadAsTheFileDoes) {
  const fs::path dir = TestDir("fused-object");
  VosselGeometry g = RandomGeometry(20000, 41);
  CanonicalizeVosselOrder(g);
  const size_t n = g.size();
  std::mt19937_64 rng(42);
  std::uniform_real_distribution<float> u(0.0f, 3.0f);
  FusedValues f;
  f.profile = "tuned";
  for (Modality m : {Modality::kRgb, Modality::kLidar, Modality::kIr}) {
    FusedModality& fm = f.by_modality[m];
    fm.channels = ChannelCount(m);
    for (size_t v = 0; v < n; ++v) {
      for (int c = 0; c < fm.channels; ++c) fm.value.push_back(u(rng));  // even where unweighed
      fm.weight.push_back(v % 3 == 0 ? 0.0f : v % 101 == 1 ? std::nanf("") : u(rng) + 0.01f);
      fm.uncertainty.push_back(u(rng));
    }
  }
  ASSERT_TRUE(WriteFused(g, f, dir / "file.vdb").ok());
  absl::StatusOr<FusedValues> from_file = ReadFused(g, dir / "file.vdb");
  ASSERT_TRUE(from_file.ok()) << from_file.status();
  absl::StatusOr<std::string> bytes = EncodeFused(g, f);
  ASSERT_TRUE(bytes.ok()) << bytes.status();
  WriteBytes(dir / "object.vdb", *bytes);
  EXPECT_EQ(GridNames(dir / "object.vdb"), (std::set<std::string>{"fused"}));
  absl::StatusOr<FusedValues> back = ReadFused(g, dir / "object.vdb");
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->profile, "tuned");
  ASSERT_EQ(back->by_modality.size(), 3u);
  size_t weighed = 0;
  for (const auto& [m, fm] : from_file->by_modality) {
    const FusedModality& b = back->by_modality.at(m);
    EXPECT_EQ(b.channels, fm.channels);
    EXPECT_EQ(b.value, fm.value);
    EXPECT_EQ(b.weight, fm.weight);
    EXPECT_EQ(b.uncertainty, fm.uncertainty);
    for (size_t v = 0; v < n; ++v) {
      if (!(f.by_modality.at(m).weight[v] > 0.0f)) {
        ASSERT_EQ(b.weight[v], 0.0f) << v;
        ASSERT_EQ(b.uncertainty[v], 0.0f) << v;
      } else {
        ++weighed;
        ASSERT_EQ(b.uncertainty[v], f.by_modality.at(m).uncertainty[v]) << v;
      }
    }
  }
  EXPECT_GT(weighed, n);  // most vossels of each modality, not none
  std::printf("fused object %.1f B/vossel, the file %.1f B/vossel (3 modalities)\n",
              double(bytes->size()) / n, double(fs::file_size(dir / "file.vdb")) / n);

  // The older layout of an object: the file's plain grids.
  absl::StatusOr<openvdb::GridCPtrVec> grids = FusedGrids(g, f);
  ASSERT_TRUE(grids.ok()) << grids.status();
  absl::StatusOr<std::string> old_bytes = internal::EncodeVdbFile(
      *grids, openvdb::MetaMap(), internal::VdbCompression::kActiveMaskOnly, "old object");
  ASSERT_TRUE(old_bytes.ok()) << old_bytes.status();
  WriteBytes(dir / "old.vdb", *old_bytes);
  absl::StatusOr<FusedValues> old_back = ReadFused(g, dir / "old.vdb");
  ASSERT_TRUE(old_back.ok()) << old_back.status();
  for (const auto& [m, fm] : from_file->by_modality) {
    EXPECT_EQ(old_back->by_modality.at(m).value, fm.value);
    EXPECT_EQ(old_back->by_modality.at(m).weight, fm.weight);
  }

  // A modality whose weight was dropped.
  openvdb::GridPtrVecPtr object;
  {
    openvdb::io::File file((dir / "object.vdb").string());
    file.open();
    object = file.getGrids();
    file.close();
  }
  auto points = openvdb::gridPtrCast<openvdb::points::PointDataGrid>((*object)[0]);
  ASSERT_TRUE(points);
  openvdb::points::dropAttribute(points->tree(), "lidar_weight");
  absl::StatusOr<std::string> partial = internal::EncodeVdbFile(
      {points}, openvdb::MetaMap(), internal::VdbCompression::kActiveMaskOnly, "partial");
  ASSERT_TRUE(partial.ok());
  WriteBytes(dir / "partial.vdb", *partial);
  absl::StatusOr<FusedValues> bad = ReadFused(g, dir / "partial.vdb");
  ASSERT_FALSE(bad.ok());
  EXPECT_EQ(bad.status().code(), absl::StatusCode::kDataLoss) << bad.status();
  EXPECT_NE(bad.status().message().find("lidar"), std::string::npos) << bad.status();

  // No vossels: the modalities and their channels still read, as from the file.
  VosselGeometry none;
  CanonicalizeVosselOrder(none);
  FusedValues empty;
  empty.by_modality[Modality::kRgb].channels = 3;
  empty.by_modality[Modality::kLidar].channels = 1;
  absl::StatusOr<std::string> empty_bytes = EncodeFused(none, empty);
  ASSERT_TRUE(empty_bytes.ok()) << empty_bytes.status();
  WriteBytes(dir / "empty.vdb", *empty_bytes);
  absl::StatusOr<FusedValues> empty_back = ReadFused(none, dir / "empty.vdb");
  ASSERT_TRUE(empty_back.ok()) << empty_back.status();
  ASSERT_EQ(empty_back->by_modality.size(), 2u);
  EXPECT_EQ(empty_back->by_modality.at(Modality::kRgb).channels, 3);
  EXPECT_EQ(empty_back->by_modality.at(Modality::kLidar).channels, 1);
  EXPECT_TRUE(empty_back->by_modality.at(Modality::kRgb).value.empty());
  // ... and an object without vossels is not read over a geometry that has some.
  absl::StatusOr<FusedValues> wrong = ReadFused(g, dir / "empty.vdb");
  ASSERT_FALSE(wrong.ok());
  EXPECT_EQ(wrong.status().code(), absl::StatusCode::kDataLoss) << wrong.status();
  fs::remove_all(dir);
}

// Claim (§7, issue "Reweighting"): what weights read keeps its precision. range to h/10 or
// better up to 300 m (h = 2 cm: 2 mm); V a multiple of 1/17 (the PCF's 17 samples) reads back
// exactly, so no V ≥ V_min test flips for any V_min; RoundToStorage gives, bit for bit, what a
// write and read of the file give.
TEST(RecordGridTest, WeightInputsKeepTheirPrecision) {
  const fs::path dir = TestDir("precision");
  VosselGeometry g = RandomGeometry(4000, 9);
  CanonicalizeVosselOrder(g);
  RecordSet in = RandomRecords(g.size(), 10);
  std::mt19937 rng(11);
  std::uniform_real_distribution<float> range(0.1f, 300.0f);
  for (size_t i = 0; i < in.size(); ++i) {
    in.range_m[i] = range(rng);
    in.vis[i] = float(int(i % 18)) / 17.0f;
  }
  RecordSet rounded = in;
  RoundToStorage(rounded);
  const fs::path path = dir / "records.vdb";
  ASSERT_TRUE(WriteRecords(g, in, path).ok());
  absl::StatusOr<RecordSet> out = ReadRecords(g, path);
  ASSERT_TRUE(out.ok()) << out.status();
  double worst_range = 0.0;
  size_t flips = 0, tests = 0;
  for (size_t i = 0; i < in.size(); ++i) {
    worst_range = std::max(worst_range, std::fabs(double(out->range_m[i]) - in.range_m[i]));
    ASSERT_EQ(out->vis[i], in.vis[i]) << "V = " << int(i % 18) << "/17 must read back exactly";
    for (int m = 0; m <= 1000; ++m) {  // V_min on a fine grid and at every multiple of 1/17
      const float v_min = m <= 982 ? float(m) / 982.0f : float(m - 983) / 17.0f;
      flips += (in.vis[i] >= v_min) != (out->vis[i] >= v_min);
      ++tests;
    }
  }
  EXPECT_LE(worst_range, 0.002) << "range must keep h/10 = 2 mm at h = 2 cm up to 300 m";
  EXPECT_EQ(flips, 0u);
  // Rounding in memory is exactly the file's round trip.
  EXPECT_EQ(rounded.value, out->value);
  EXPECT_EQ(rounded.range_m, out->range_m);
  EXPECT_EQ(rounded.cos_inc, out->cos_inc);
  EXPECT_EQ(rounded.foot_major_m, out->foot_major_m);
  EXPECT_EQ(rounded.foot_minor_m, out->foot_minor_m);
  EXPECT_EQ(rounded.vis, out->vis);
  EXPECT_EQ(rounded.conf, out->conf);
  EXPECT_EQ(rounded.uv_px, out->uv_px);
  std::printf("weight inputs: %zu records, worst range error %.3g m to 300 m; %zu V >= V_min "
              "tests, %zu flipped\n", in.size(), worst_range, tests, flips);
}

// Claim: pixel coordinates outside the 16-bit span [0, 16384) px (a wider image, or a sample
// off its image's edge) keep float for the whole file, exactly; within it, RoundToStorage gives
// what a write and read give, bit for bit.
TEST(RecordGridTest, UvOutsideTheSixteenBitSpanKeepsFloat) {
  const fs::path dir = TestDir("uv-wide");
  VosselGeometry g = RandomGeometry(1000, 12);
  CanonicalizeVosselOrder(g);
  RecordSet in = RandomRecords(g.size(), 13);
  ASSERT_GT(in.size(), 4u);
  in.uv_px[0] = 20000.5f;   // a 24k-wide panorama
  in.uv_px[3] = -0.25f;     // off the edge
  RecordSet rounded = in;
  RoundToStorage(rounded);
  EXPECT_EQ(rounded.uv_px[0], 20000.5f);
  EXPECT_EQ(rounded.uv_px[3], -0.25f);
  ASSERT_TRUE(WriteRecords(g, in, dir / "records.vdb").ok());
  absl::StatusOr<std::vector<AttributeInfo>> list = ListRecordAttributes(dir / "records.vdb");
  ASSERT_TRUE(list.ok()) << list.status();
  for (const AttributeInfo& a : *list) {
    if (a.name == "uv") EXPECT_EQ(a.codec, "null") << "a file with such a uv keeps float";
  }
  absl::StatusOr<RecordSet> out = ReadRecords(g, dir / "records.vdb");
  ASSERT_TRUE(out.ok()) << out.status();
  EXPECT_EQ(out->uv_px, in.uv_px);  // float: exact, rounded nowhere
  // A file within the span: the rounding in memory is the file's.
  RecordSet narrow = RandomRecords(g.size(), 14);
  RecordSet narrow_rounded = narrow;
  RoundToStorage(narrow_rounded);
  ASSERT_TRUE(WriteRecords(g, narrow, dir / "narrow.vdb").ok());
  absl::StatusOr<RecordSet> back = ReadRecords(g, dir / "narrow.vdb");
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->uv_px, narrow_rounded.uv_px);
  size_t moved = 0;
  for (size_t i = 0; i < narrow.uv_px.size(); ++i) moved += narrow.uv_px[i] != back->uv_px[i];
  std::printf("uv: %zu of %zu coordinates rounded to the 16-bit step\n", moved,
              narrow.uv_px.size());
  EXPECT_GT(moved, 0u);
  fs::remove_all(dir);
}

// Claim (the records' codec): EncodeHalves gives, bit for bit, the half Imath makes of each
// float (round to nearest, ties to even), whatever instruction set runs it: every sign,
// exponent and top 10 mantissa bits with low bits 0, 1 and about the rounding boundaries
// (0x0fff, 0x1000, 0x1001, 0x17ff, 0x1800, 0x1fff): zeros, denormals, ties, overflow,
// infinities, quiet and signalling NaNs; and a stride through all 2^32 patterns.
TEST(RecordGridTest, EncodeHalvesIsImathsHalf) {
  std::vector<float> in;
  const uint32_t lows[] = {0x0, 0x1, 0x0fff, 0x1000, 0x1001, 0x17ff, 0x1800, 0x1fff};
  for (uint32_t top = 0; top < (1u << 19); ++top) {  // sign, exponent, 10 mantissa bits
    for (uint32_t low : lows) {
      const uint32_t bits = (top << 13) | low;
      float f;
      std::memcpy(&f, &bits, 4);
      in.push_back(f);
    }
  }
  for (uint64_t bits = 0; bits < (uint64_t(1) << 32); bits += 9973) {
    const uint32_t b = uint32_t(bits);
    float f;
    std::memcpy(&f, &b, 4);
    in.push_back(f);
  }
  in.push_back(0.1f);  // an odd tail past the last whole group of eight
  std::vector<uint16_t> want(in.size());
  for (size_t k = 0; k < in.size(); ++k) {
    want[k] = openvdb::math::half(in[k]).bits();
  }
  for (const memory::Isa isa :
       {memory::Isa::kBaseline, memory::Isa::kAvx2, memory::Isa::kX86_64_V4}) {
    memory::SetIsaCap(isa);
    std::vector<uint16_t> got(in.size());
    EncodeHalves(in.data(), got.data(), in.size());
    size_t differ = 0;
    uint32_t first_bits = 0;
    for (size_t k = 0; k < in.size(); ++k) {
      if (got[k] != want[k] && differ++ == 0) std::memcpy(&first_bits, &in[k], 4);
    }
    EXPECT_EQ(differ, 0u) << "ISA cap " << int(isa) << ": " << differ << " of " << in.size()
                          << " differ, the first one's float bits 0x" << std::hex << first_bits;
  }
  memory::SetIsaCap(memory::Isa::kX86_64_V4);
}

}  // namespace
}  // namespace vasl::records

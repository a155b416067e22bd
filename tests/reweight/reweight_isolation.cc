// VASL-MODEL §7: reweighting reads records only. This executable links vasl::reweight and
// nothing that does visibility, projection or image sampling (tests/CMakeLists.txt checks the
// link closure), and reweights a tiled project: were the reweight to call any of them, it would
// not link. It also shows that fusing tile by tile gives, value for value, the fusion of the
// whole project.
#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <random>

#include <gtest/gtest.h>

#include "lattice/fusion/fuse.h"
#include "lattice/records/record_grid.h"
#include "lattice/reweight/profiles.h"
#include "lattice/reweight/reweight_flow.h"
#include "lattice/store/project_store.h"

namespace vasl::reweight {
namespace {
namespace fs = std::filesystem;

// A project of `n` random vossels over several 8³ tiles, each with 1-4 RGB or LiDAR records.
store::Snapshot RandomSnapshot(size_t n, double h) {
  store::Snapshot s;
  s.geometry.vossel_size_m = h;
  std::mt19937 rng(5);
  std::uniform_int_distribution<int> coord(-20, 20), count(1, 4), source(1, 6);
  std::uniform_real_distribution<float> u(0.0f, 1.0f);
  std::set<std::tuple<int, int, int>> used;
  while (s.geometry.coord.size() < n) {
    const int x = coord(rng), y = coord(rng), z = coord(rng);
    if (!used.insert({x, y, z}).second) continue;
    s.geometry.coord.emplace_back(x, y, z);
    s.geometry.point_count.push_back(3);
    s.geometry.centroid_m.emplace_back(float(x * h), float(y * h), float(z * h));
    s.geometry.normal.emplace_back(0.0f, 0.0f, 1.0f);
    s.geometry.covariance_m2.push_back({1e-6f, 0, 0, 1e-6f, 0, 1e-6f});
    s.geometry.sums.emplace_back();
  }
  records::CanonicalizeVosselOrder(s.geometry);
  records::RecordSet& r = s.records;
  for (size_t k = 0; k < n; ++k) {
    const int m = count(rng);
    for (int j = 0; j < m; ++j) {
      const size_t i = r.size();
      r.Resize(i + 1);
      r.vossel[i] = int32_t(k);
      r.scan[i] = source(rng);
      r.modality[i] = int8_t(r.scan[i] == 1 ? records::Modality::kLidar : records::Modality::kRgb);
      for (int c = 0; c < 3; ++c) r.value[i * 3 + c] = u(rng);
      r.range_m[i] = 1.0f + 20.0f * u(rng);
      r.cos_inc[i] = u(rng);
      r.foot_major_m[i] = 0.02f * u(rng);
      r.foot_minor_m[i] = r.foot_major_m[i] * u(rng);
      r.vis[i] = float(int(17 * u(rng))) / 17.0f;
      for (int f = 0; f < records::kConfidenceCount; ++f) {
        r.conf[i * records::kConfidenceCount + f] = 0.5f + 0.5f * u(rng);
      }
      r.uv_px[2 * i] = u(rng);
      r.uv_px[2 * i + 1] = u(rng);
      r.flags[i] = 0;
      r.batch[i] = 1;
    }
  }
  r.SortByVossel();
  records::RoundToStorage(r);
  s.fused = *fusion::Fuse(r, n, h, fusion::WeightingProfile{});
  return s;
}

TEST(ReweightIsolationTest, ReweightsFromRecordsAloneTileByTile) {
  const fs::path root = fs::temp_directory_path() / ("vasl-reweight-iso-" + std::to_string(::getpid()));
  fs::remove_all(root);
  fs::create_directories(root);
  store::ProjectSettings settings;
  settings.vossel_size_m = 0.05;
  settings.tile_vossels = 8;
  auto st = store::ProjectStore::Create(root / "p", "p", settings);
  ASSERT_TRUE(st.ok()) << st.status();
  const store::Snapshot snap = RandomSnapshot(3000, settings.vossel_size_m);
  store::CommitPlan plan;
  plan.made_by = "test";
  plan.replace_all = true;
  ASSERT_TRUE((*st)->Commit(snap, plan).ok());

  fusion::WeightingProfile p;
  p.name = "steep";
  p.alpha = 3.0;
  p.beta = 0.5;
  p.rho = 1.5;
  p.v_min = 0.2;
  p.proximity_m = 4.0;
  p.kappa = {2.0, 1.0, 0.5, 0.0};
  p.scan_gain[3] = 0.25;
  p.channel_gain[2] = {1.2, 0.9, 1.05};
  auto made = CreateProfile(**st, p);
  ASSERT_TRUE(made.ok()) << made.status();
  int64_t calls = 0;
  auto r = Reweight(**st, made->profile, [&](int64_t, int64_t) {
    ++calls;
    return absl::OkStatus();
  });
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->version, 2);
  EXPECT_EQ(r->records, int64_t(snap.records.size()));
  EXPECT_GT(r->tiles, 10);
  EXPECT_EQ(calls, r->tiles);
  std::printf("reweight: %lld tiles, %lld records, %lld bytes written, %.3f s\n",
              (long long)r->tiles, (long long)r->records, (long long)r->bytes_written, r->seconds);

  // Tile by tile equals the whole project fused at once, bit for bit.
  auto loaded = (*st)->LoadSnapshot(r->version, {r->layer});
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  const records::FusedValues whole =
      *fusion::Fuse((*loaded)->records, (*loaded)->geometry.size(), settings.vossel_size_m, made->profile);
  const records::FusedValues& tiled = (*loaded)->profile_fused.at(r->layer);
  ASSERT_EQ(whole.by_modality.size(), tiled.by_modality.size());
  for (const auto& [m, f] : whole.by_modality) {
    EXPECT_EQ(f.value, tiled.by_modality.at(m).value);
    EXPECT_EQ(f.weight, tiled.by_modality.at(m).weight);
    EXPECT_EQ(f.uncertainty, tiled.by_modality.at(m).uncertainty);
  }
  // The version shares every other object with the one before.
  auto before = (*st)->LoadManifest(1), after = (*st)->LoadManifest(2);
  for (const auto& [key, layers] : before->tiles) {
    for (const auto& [layer, e] : layers) EXPECT_EQ(after->tiles.at(key).at(layer).object, e.object);
    EXPECT_TRUE(after->tiles.at(key).count(r->layer));
  }
  // Again under the same revision: nothing to do.
  auto again = Reweight(**st, made->profile);
  ASSERT_TRUE(again.ok());
  EXPECT_TRUE(again->unchanged);
  EXPECT_EQ(again->version, 2);
  fs::remove_all(root);
}

}  // namespace
}  // namespace vasl::reweight

// VASL-MODEL §7 as a user drives it: profiles, reweighting a stored project, renders and
// provenance queries under a profile, fused layers kept up to date by later ingests, pinning.
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <filesystem>

#include <gtest/gtest.h>

#include "lattice/engine.h"
#include "lattice/fusion/weight.h"
#include "lattice/geometry/footprint.h"
#include "lattice/store/project_store.h"
#include "tests/scenes/synthetic_scene.h"

namespace vasl {
namespace {
namespace fs = std::filesystem;

constexpr double kVosselM = 0.05;

fusion::WeightingProfile Sharp() {
  fusion::WeightingProfile p;
  p.name = "sharp";
  p.alpha = 2.0;
  p.beta = 0.5;
  p.rho = 0.5;
  p.v_min = 0.3;
  p.proximity_m = 1.5;
  p.kappa = {2.0, 1.0, 1.0, 0.0};
  p.scan_gain[4] = 0.5;                 // the second scan's camera counts half
  p.channel_gain[2] = {1.1, 0.9, 1.0};  // the first scan's camera, a colour cast undone
  return p;
}

class ReweightTest : public ::testing::Test {
 protected:
  void SetUp() override {
    root_ = fs::temp_directory_path() / ("vasl-reweight-" + std::to_string(::getpid()));
    fs::remove_all(root_);
    auto engine = Engine::Open(root_);
    ASSERT_TRUE(engine.ok()) << engine.status();
    engine_ = std::move(*engine);
  }
  void TearDown() override { fs::remove_all(root_); }

  void Create(const std::string& name, int keep_versions = 20) {
    store::ProjectSettings settings;
    settings.vossel_size_m = kVosselM;
    settings.keep_versions = keep_versions;
    settings.tile_vossels = 32;
    ASSERT_TRUE(engine_->CreateProject(name, settings).ok());
  }
  void Ingest(const std::string& project, size_t station) {
    auto scan = scenes::MakeScanInput(room_, station, scenes::LidarSettings::Small(station + 1), 512, 2);
    ASSERT_TRUE(scan.ok()) << scan.status();
    auto r = engine_->IngestScan(project, *scan);
    ASSERT_TRUE(r.ok()) << r.status();
  }
  store::Manifest Manifest(const std::string& project, int64_t version) {
    auto st = store::ProjectStore::Open(root_ / project);
    EXPECT_TRUE(st.ok()) << st.status();
    return *(*st)->LoadManifest(version);
  }
  /// Tiles (of `layers` in both) whose objects differ between two manifests.
  static int Differing(const store::Manifest& a, const store::Manifest& b,
                       const std::vector<std::string>& layers, int* compared) {
    int differ = 0;
    *compared = 0;
    EXPECT_EQ(a.tiles.size(), b.tiles.size());
    for (const auto& [key, la] : a.tiles) {
      auto it = b.tiles.find(key);
      if (it == b.tiles.end()) {
        ++differ;
        continue;
      }
      for (const std::string& layer : layers) {
        ++*compared;
        if (!la.count(layer) || !it->second.count(layer) ||
            la.at(layer).object != it->second.at(layer).object) {
          ++differ;
        }
      }
    }
    return differ;
  }

  fs::path root_;
  std::unique_ptr<Engine> engine_;
  const scenes::SyntheticRoom room_ = scenes::SyntheticRoom::Default();
};

// Claim (§7): a reweight under a new profile gives the same fused tiles, bit for bit (same
// content hashes), as a fresh ingest of the same scans under that profile; later ingests keep
// the profile's layer on every tile they rewrite, so both projects stay equal.
TEST_F(ReweightTest, ReweightEqualsFreshIngestUnderTheProfile) {
  Create("a");
  Create("b");
  for (size_t i = 0; i < 2; ++i) Ingest("a", i);
  auto made = engine_->CreateProfile("a", Sharp());
  ASSERT_TRUE(made.ok()) << made.status();
  EXPECT_EQ(made->profile.version, 1);
  auto rw = engine_->Reweight("a", "sharp", 0);
  ASSERT_TRUE(rw.ok()) << rw.status();
  EXPECT_FALSE(rw->unchanged);
  EXPECT_EQ(rw->version, 3);
  const std::string layer = store::FusedLayerName("sharp", 1);
  EXPECT_EQ(rw->layer, layer);

  ASSERT_TRUE(engine_->CreateProfile("b", Sharp()).ok());
  ASSERT_TRUE(engine_->SetActiveProfile("b", "sharp").ok());
  for (size_t i = 0; i < 2; ++i) Ingest("b", i);
  int compared = 0;
  const int differ = Differing(Manifest("a", 3), Manifest("b", 2),
                               {store::kLayerGeometry, store::kLayerRecords,
                                store::kLayerFusedDefault, layer},
                               &compared);
  std::printf("reweight v3 of a vs fresh ingest v2 of b under 'sharp': %d of %d tile objects "
              "differ; reweight read %lld records in %lld tiles in %.3f s, wrote %lld bytes\n",
              differ, compared, (long long)rw->records, (long long)rw->tiles, rw->seconds,
              (long long)rw->bytes_written);
  EXPECT_EQ(differ, 0);

  // A third scan into both: the profile's layer is recomputed where records change.
  Ingest("a", 2);
  Ingest("b", 2);
  const int differ3 = Differing(Manifest("a", 4), Manifest("b", 3),
                                {store::kLayerRecords, store::kLayerFusedDefault, layer}, &compared);
  std::printf("after a third scan: %d of %d tile objects differ\n", differ3, compared);
  EXPECT_EQ(differ3, 0);
  auto again = engine_->Reweight("a", "sharp", 0);
  ASSERT_TRUE(again.ok());
  EXPECT_TRUE(again->unchanged) << "the ingest kept the layer complete";
}

// Claim (§7, §8): a render under a profile without fused tiles fuses on the fly and says so;
// after a reweight it reads the stored tiles and gives the same image, bit for bit. A render
// under another profile differs from the default's.
TEST_F(ReweightTest, RenderUnderAProfileStoredOrOnTheFly) {
  Create("r");
  for (size_t i = 0; i < 2; ++i) Ingest("r", i);
  ASSERT_TRUE(engine_->CreateProfile("r", Sharp()).ok());
  RenderRequest req;
  req.pose = room_.NovelViews()[0];
  req.width_px = 256;
  req.height_px = 128;
  req.profile = "sharp";
  auto fly = engine_->Render("r", req);
  ASSERT_TRUE(fly.ok()) << fly.status();
  EXPECT_TRUE(fly->fused_on_the_fly);
  EXPECT_EQ(fly->profile, "sharp");
  ASSERT_TRUE(engine_->Reweight("r", "sharp", 0).ok());
  auto stored = engine_->Render("r", req);
  ASSERT_TRUE(stored.ok()) << stored.status();
  EXPECT_FALSE(stored->fused_on_the_fly);
  EXPECT_EQ(stored->rgb, fly->rgb);
  EXPECT_EQ(stored->uncertainty, fly->uncertainty);
  req.profile = "";  // the active profile: the default
  auto plain = engine_->Render("r", req);
  ASSERT_TRUE(plain.ok());
  EXPECT_EQ(plain->profile, "default");
  EXPECT_FALSE(plain->fused_on_the_fly);
  double diff = 0.0;
  for (size_t i = 0; i < plain->rgb.size(); ++i) diff = std::max(diff, double(std::abs(plain->rgb[i] - stored->rgb[i])));
  std::printf("render under 'sharp' vs default: max |ΔC| %.3g\n", diff);
  EXPECT_GT(diff, 1e-3);
  req.profile = "missing";
  EXPECT_EQ(engine_->Render("r", req).status().code(), absl::StatusCode::kNotFound);
}

// Claim (§7): the provenance query lists a vossel's records with the weight each gets under
// the profile, as RecordWeight computes it from the record's own fields.
TEST_F(ReweightTest, RecordsAtAPointCarryTheirWeights) {
  Create("q");
  for (size_t i = 0; i < 2; ++i) Ingest("q", i);
  fusion::WeightingProfile p = Sharp();
  p.proximity_m = 0.0;  // r_min is per vossel; keep the check to the record's own fields
  p.name = "flat";
  ASSERT_TRUE(engine_->CreateProfile("q", p).ok());
  const Eigen::Vector3d lo(-10, -10, -10), hi(10, 10, 10);
  auto all = engine_->QueryRecords("q", 0, lo, hi, "flat", 200);
  ASSERT_TRUE(all.ok()) << all.status();
  ASSERT_EQ(all->rows.size(), 200u);
  EXPECT_TRUE(all->truncated);
  const flows::RecordRow& first = all->rows.front();
  const Eigen::Vector3d at = first.centroid_m.cast<double>();
  auto one = engine_->QueryRecords("q", 0, at, at, "flat", 1000);
  ASSERT_TRUE(one.ok()) << one.status();
  ASSERT_GE(one->rows.size(), 1u);
  EXPECT_EQ(one->vossels, 1);
  int checked = 0;
  for (const auto& batch : {all->rows, one->rows}) {
    for (const flows::RecordRow& r : batch) {
      EXPECT_FALSE(r.scan_name.empty());
      fusion::WeightInputs in;
      in.vis = r.vis;
      in.cos_inc = r.cos_inc;
      in.foot_major_m = r.foot_major_m;
      in.foot_minor_m = r.foot_minor_m;
      in.conf = r.conf.data();
      in.scan = r.source;
      in.derived = (r.flags & records::kFlagDerived) != 0;
      const double w = fusion::RecordWeight(p, in, geometry::TargetResolutionM(kVosselM));
      EXPECT_FLOAT_EQ(r.weight, float(w));
      ++checked;
    }
  }
  std::printf("records query: %d records checked against RecordWeight\n", checked);
  EXPECT_EQ(engine_->QueryRecords("q", 0, hi, lo, "flat", 10).status().code(),
            absl::StatusCode::kInvalidArgument);
}

// Claim: a pinned version survives retention; profiles keep every revision readable.
TEST_F(ReweightTest, PinnedVersionSurvivesAndRevisionsStayReadable) {
  Create("h", /*keep_versions=*/1);
  Ingest("h", 0);
  ASSERT_TRUE(engine_->SetPinned("h", 1, true).ok());
  fusion::WeightingProfile p = Sharp();
  ASSERT_TRUE(engine_->CreateProfile("h", p).ok());
  p.alpha = 4.0;
  auto second = engine_->CreateProfile("h", p);
  ASSERT_TRUE(second.ok());
  EXPECT_EQ(second->profile.version, 2);
  for (int r = 0; r < 3; ++r) ASSERT_TRUE(engine_->Reweight("h", "sharp", r == 0 ? 1 : 2).ok());
  Ingest("h", 1);
  auto versions = engine_->ListVersions("h");
  ASSERT_TRUE(versions.ok());
  bool has_pinned = false;
  for (const store::VersionInfo& v : *versions) has_pinned = has_pinned || (v.version == 1 && v.pinned);
  EXPECT_TRUE(has_pinned) << "pinned version 1 was removed by retention";
  EXPECT_LE(versions->size(), 3u);
  auto r1 = engine_->GetProfile("h", "sharp", 1);
  ASSERT_TRUE(r1.ok());
  EXPECT_EQ(r1->profile.alpha, 2.0);
  EXPECT_EQ(engine_->GetProfile("h", "sharp", 2)->profile.alpha, 4.0);
  EXPECT_EQ(engine_->GetProfile("h", "sharp", 0)->profile.version, 2);
  fusion::WeightingProfile bad = Sharp();
  bad.v_min = 2.0;
  EXPECT_EQ(engine_->CreateProfile("h", bad).status().code(), absl::StatusCode::kInvalidArgument);
  bad = Sharp();
  bad.name = "default";
  EXPECT_EQ(engine_->CreateProfile("h", bad).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(engine_->SetActiveProfile("h", "nope").code(), absl::StatusCode::kNotFound);
}

// Claim (history): a rollback to a kept version is a new commit that gives back that version's
// tiles and fused layers object for object, and its scans (deleted ones return, later ones
// leave, their names free again); what made each version is listed.
TEST_F(ReweightTest, RollbackGivesBackAVersionExactly) {
  Create("b");
  for (size_t i = 0; i < 2; ++i) Ingest("b", i);  // v1, v2
  ASSERT_TRUE(engine_->CreateProfile("b", Sharp()).ok());
  ASSERT_TRUE(engine_->Reweight("b", "sharp", 0).ok());  // v3
  Ingest("b", 2);                                         // v4
  auto names = [&](int64_t v) {
    auto st = store::ProjectStore::Open(root_ / "b");
    std::vector<std::string> out;
    const std::vector<store::ScanInfo> scans = *(*st)->ListScans(v);
    for (const store::ScanInfo& s : scans) out.push_back(s.name);
    return out;
  };
  const std::vector<std::string> at3 = names(3);
  ASSERT_EQ(at3.size(), 2u);
  ASSERT_TRUE(engine_->DeleteScan("b", at3[0]).ok());  // v5
  RenderRequest req;
  req.pose = room_.NovelViews()[0];
  req.width_px = 256;
  req.height_px = 128;
  req.profile = "sharp";
  req.version = 3;
  auto before = engine_->Render("b", req);
  ASSERT_TRUE(before.ok()) << before.status();

  auto rolled = engine_->Rollback("b", 3);
  ASSERT_TRUE(rolled.ok()) << rolled.status();
  EXPECT_EQ(rolled->version, 6);
  int compared = 0;
  const store::Manifest m3 = Manifest("b", 3), m6 = Manifest("b", 6);
  const int differ = Differing(m3, m6, {store::kLayerGeometry, store::kLayerRecords,
                                        store::kLayerFusedDefault, store::FusedLayerName("sharp", 1)},
                               &compared);
  EXPECT_EQ(differ, 0) << "of " << compared;
  EXPECT_EQ(m3.reach.size(), m6.reach.size());
  EXPECT_EQ(names(6), at3) << "the deleted scan is back, the later one gone";
  req.version = 0;
  auto after = engine_->Render("b", req);
  ASSERT_TRUE(after.ok()) << after.status();
  EXPECT_FALSE(after->fused_on_the_fly);
  EXPECT_EQ(after->rgb, before->rgb);
  EXPECT_EQ(after->depth_m, before->depth_m);
  auto info = engine_->GetProject("b");
  ASSERT_TRUE(info.ok());
  EXPECT_EQ(info->scan_count, 2);
  Ingest("b", 2);  // the scan that left can come in again: v7
  EXPECT_EQ(names(7).size(), 3u);
  auto versions = engine_->ListVersions("b");
  ASSERT_TRUE(versions.ok());
  std::vector<std::string> made_by;
  for (const store::VersionInfo& v : *versions) made_by.push_back(v.made_by);
  std::printf("history:");
  for (const std::string& m : made_by) std::printf(" [%s]", m.c_str());
  std::printf("\nrollback: %d tile objects of version 3 given back unchanged, %d differ\n",
              compared - differ, differ);
  ASSERT_GE(made_by.size(), 3u);
  EXPECT_EQ(made_by[made_by.size() - 2], "rollback to version 3");
  EXPECT_EQ(made_by[2], "reweight under profile sharp revision 1");
  EXPECT_EQ(engine_->Rollback("b", 7).status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace vasl

// Bounded memory for readers (issue "A store that grows"): a render or a records query of a
// version larger than the engine's max_snapshot_bytes reads its tiles in groups within that
// budget, one after another, and gives the answer a reader of the whole version gives. The
// corridor site's first six stations (h = 5 cm, tiles of 32 vossels: many tiles) are ingested
// by an engine with the default budget, which renders and queries them whole; an engine with a
// budget of a fifth of the version's estimate asks the same and must agree pixel by pixel and
// record by record.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <unistd.h>

#include "lattice/engine.h"
#include "lattice/flows/tile_budget.h"
#include "lattice/render/encode.h"
#include "tests/scenes/corridor_site.h"

namespace vasl {
namespace {

namespace fs = std::filesystem;

constexpr int kPanoW = 512, kPanoH = 256;
constexpr size_t kStations = 6;

// Pixels where two renders differ in any per-pixel value (depth, rgb, normal, U, alpha and,
// when deep, every layer's depth, rgb and alpha).
int64_t DifferingPixels(const RenderImage& a, const RenderImage& b) {
  EXPECT_EQ(a.width_px, b.width_px);
  EXPECT_EQ(a.height_px, b.height_px);
  EXPECT_EQ(a.layers, b.layers);
  const size_t n = a.depth_m.size(), L = size_t(a.layers);
  int64_t differ = 0;
  auto same = [](float x, float y) { return x == y || (std::isnan(x) && std::isnan(y)); };
  for (size_t p = 0; p < n; ++p) {
    bool eq = same(a.depth_m[p], b.depth_m[p]) && same(a.uncertainty[p], b.uncertainty[p]) &&
              same(a.alpha[p], b.alpha[p]);
    for (int c = 0; c < 3 && eq; ++c) {
      eq = same(a.rgb[3 * p + c], b.rgb[3 * p + c]) &&
           same(a.normal[3 * p + c], b.normal[3 * p + c]);
    }
    if (L > 1 && eq) {
      eq = a.layer_count[p] == b.layer_count[p];
      for (size_t l = 0; l < L && eq; ++l) {
        eq = same(a.deep_depth_m[p * L + l], b.deep_depth_m[p * L + l]) &&
             same(a.deep_alpha[p * L + l], b.deep_alpha[p * L + l]);
        for (int c = 0; c < 3 && eq; ++c) {
          eq = same(a.deep_rgb[3 * (p * L + l) + c], b.deep_rgb[3 * (p * L + l) + c]);
        }
      }
    }
    differ += eq ? 0 : 1;
  }
  return differ;
}

class BoundedReadTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new fs::path(fs::temp_directory_path() /
                        ("vasl-bounded-read-" + std::to_string(::getpid())));
    fs::remove_all(*dir_);
    auto engine = Engine::Open(*dir_);
    ASSERT_TRUE(engine.ok()) << engine.status();
    store::ProjectSettings settings;
    settings.vossel_size_m = 0.05;
    settings.tile_vossels = 32;
    ASSERT_TRUE((*engine)->CreateProject("site", settings).ok());
    const scenes::CorridorSite site = scenes::CorridorSite::Default();
    for (size_t s = 0; s < kStations; ++s) {
      auto scan = scenes::MakeScanInput(site, s, scenes::LidarSettings::Small(s + 1), 1024, 2);
      ASSERT_TRUE(scan.ok()) << scan.status();
      auto r = (*engine)->IngestScan("site", *scan);
      ASSERT_TRUE(r.ok()) << r.status();
    }
    fusion::WeightingProfile sharp;  // a stored profile without fused tiles: fused per render
    sharp.name = "sharp";
    sharp.alpha = 2.0;
    ASSERT_TRUE((*engine)->CreateProfile("site", sharp).ok());
    fusion::WeightingProfile kept = sharp;  // and one reweighted: its fused tiles are read
    kept.name = "kept";
    kept.beta = 0.5;
    ASSERT_TRUE((*engine)->CreateProfile("site", kept).ok());
    ASSERT_TRUE((*engine)->Reweight("site", "kept", 0).ok());
    auto st = store::ProjectStore::Open(*dir_ / "site");
    ASSERT_TRUE(st.ok()) << st.status();
    auto manifest = (*st)->LoadManifest((*st)->head_version());
    ASSERT_TRUE(manifest.ok()) << manifest.status();
    tiles_ = int64_t(manifest->tiles.size());
    whole_bytes_ = flows::VersionMemoryBytes(*manifest, true, 1);
  }
  static void TearDownTestSuite() {
    fs::remove_all(*dir_);
    delete dir_;
  }

  // The engine that holds whole versions and the one bounded to a fifth of this one.
  static std::unique_ptr<Engine> Open(bool bounded) {
    EngineLimits limits;
    if (bounded) limits.max_snapshot_bytes = whole_bytes_ / 5;
    auto engine = Engine::Open(*dir_, limits);
    EXPECT_TRUE(engine.ok()) << engine.status();
    return engine.ok() ? std::move(*engine) : nullptr;
  }

  // A render of "site" from the corridor's first novel view as an RGBZ image sent back (§10);
  // an empty image when the render fails.
  static BackProjectInput Retouch() {
    RenderRequest req;
    req.pose = scenes::CorridorSite::Default().NovelViews()[0];
    req.width_px = kPanoW;
    req.height_px = kPanoH;
    BackProjectInput in;
    in.name = "retouch";
    in.pose = req.pose;
    auto image = Open(false)->Render("site", req);
    EXPECT_TRUE(image.ok()) << image.status();
    if (image.ok()) in.image = *render::EncodeExr(*image);
    return in;
  }

  // Renders `req` whole and bounded; expects the same image, printed with the groups taken.
  void ExpectSameRender(const char* what, RenderRequest req) {
    req.pose = scenes::CorridorSite::Default().NovelViews()[0];
    auto whole = Open(false)->Render("site", req);
    ASSERT_TRUE(whole.ok()) << whole.status();
    auto bounded_engine = Open(true);
    int64_t rows = 0;
    req.rows_done = [&rows](const RenderImage&, int begin, int end) {
      rows += end - begin;
      return absl::OkStatus();
    };
    auto bounded = bounded_engine->Render("site", req);
    ASSERT_TRUE(bounded.ok()) << bounded.status();
    const int64_t differ = DifferingPixels(*whole, *bounded);
    std::printf("  %s: whole in %d group, bounded in %d groups reading %lld of %lld tiles; "
                "%lld hit pixels, %lld differ\n", what, whole->tile_groups, bounded->tile_groups,
                (long long)bounded->tiles_read, (long long)bounded->tiles_total,
                (long long)whole->hit_pixels, (long long)differ);
    EXPECT_EQ(bounded->tiles_total, tiles_);
    EXPECT_LE(bounded->tiles_read, tiles_);
    EXPECT_EQ(whole->tile_groups, 1);
    // Geometry alone fits in two groups; with records (η > 0, colour detail, a profile
    // without fused tiles) in five or more. Deep output takes a pass per layer.
    // Several groups, or few tiles: from inside the first room the rays stop at its walls
    // and the tiles behind them are never read (RayReach); deeper layers see through.
    EXPECT_TRUE(bounded->tile_groups >= 2 || bounded->tiles_read < tiles_ / 2);
    if (req.layers == 1) EXPECT_LT(bounded->tiles_read, tiles_ * 9 / 10);
    int64_t deeper = 0;  // pixels with a second surface layer
    for (uint8_t c : whole->layer_count) deeper += c >= 2 ? 1 : 0;
    if (req.layers > 1) {
      std::printf("  %lld pixels have a second layer\n", (long long)deeper);
      EXPECT_GT(deeper, whole->hit_pixels / 20);  // tables and partitions: 8.7% here
    }
    EXPECT_GT(whole->hit_pixels, int64_t(req.width_px) * req.height_px / 2);
    EXPECT_EQ(differ, 0);
    EXPECT_EQ(bounded->hit_pixels, whole->hit_pixels);
    EXPECT_EQ(bounded->colourless_pixels, whole->colourless_pixels);
    EXPECT_EQ(bounded->fused_on_the_fly, whole->fused_on_the_fly);
    EXPECT_EQ(bounded->version, whole->version);
    EXPECT_GT(bounded->render_id, whole->render_id);  // recorded once, as any render
    EXPECT_EQ(rows, req.height_px);                   // every row streamed once
  }

  static fs::path* dir_;
  static int64_t tiles_;
  static int64_t whole_bytes_;
};
fs::path* BoundedReadTest::dir_ = nullptr;
int64_t BoundedReadTest::tiles_ = 0;
int64_t BoundedReadTest::whole_bytes_ = 0;

// Claim: the groups cover every tile once, and each fits the budget unless it is one tile.
TEST_F(BoundedReadTest, GroupsFitTheBudget) {
  auto st = store::ProjectStore::Open(*dir_ / "site");
  ASSERT_TRUE(st.ok());
  auto manifest = (*st)->LoadManifest((*st)->head_version());
  ASSERT_TRUE(manifest.ok());
  const int64_t budget = whole_bytes_ / 5;
  const auto groups = flows::TileGroups(*manifest, true, 1, budget);
  size_t covered = 0;
  std::set<tiles::TileKey> seen;
  for (const auto& g : groups) {
    covered += g.size();
    seen.insert(g.begin(), g.end());
    const int64_t bytes = flows::VersionMemoryBytes(*manifest, true, 1, &g);
    EXPECT_TRUE(bytes <= budget || g.size() == 1) << bytes << " > " << budget;
  }
  std::printf("  %lld tiles, version estimated at %.1f MB, budget %.1f MB: %zu groups\n",
              (long long)tiles_, whole_bytes_ / 1e6, budget / 1e6, groups.size());
  EXPECT_EQ(covered, manifest->tiles.size());
  EXPECT_EQ(seen.size(), manifest->tiles.size());
  EXPECT_GE(groups.size(), 5u);
}

TEST_F(BoundedReadTest, EquirectRenderIsTheWholeOne) {
  RenderRequest req;
  req.width_px = kPanoW;
  req.height_px = kPanoH;
  ExpectSameRender("equirect", req);
}

TEST_F(BoundedReadTest, ViewTermDeepLayersAndPinholeAreTheWholeOnes) {
  RenderRequest req;
  req.width_px = kPanoW;
  req.height_px = kPanoH;
  req.eta = 2.0;
  ExpectSameRender("eta 2", req);
  req.eta = 0.0;
  req.layers = 3;
  ExpectSameRender("3 layers", req);
  req.layers = 1;
  req.projection = render::Projection::kPinhole;
  req.width_px = 320;
  req.height_px = 240;
  req.pinhole.width_px = 320;
  req.pinhole.height_px = 240;
  req.pinhole.fx_px = req.pinhole.fy_px = 200.0;
  req.pinhole.cx_px = 160.0;
  req.pinhole.cy_px = 120.0;
  ExpectSameRender("pinhole", req);
}

TEST_F(BoundedReadTest, ColourDetailAndProfilesAreTheWholeOnes) {
  RenderRequest req;
  req.width_px = kPanoW;
  req.height_px = kPanoH;
  req.colour_detail = render::ColourDetail::kSourceImages;
  ExpectSameRender("colour detail", req);
  req.colour_detail = render::ColourDetail::kVossel;
  req.profile = "sharp";
  ExpectSameRender("profile fused per render", req);
  req.profile = "kept";
  ExpectSameRender("profile with fused tiles", req);
}

// Claim: an ingest, a back-projection or a deletion whose HEAD exceeds the budget reads HEAD
// without records and then the records of the tiles it rewrites only, and commits the very
// tiles a change holding the whole version commits: every tile object (geometry, records,
// fused) and reach raster the same.
TEST_F(BoundedReadTest, ChangesWithinTheBudgetWriteTheSameTiles) {
  auto engine = Open(true);
  store::ProjectSettings settings;
  settings.vossel_size_m = 0.05;
  settings.tile_vossels = 32;
  ASSERT_TRUE(engine->CreateProject("scoped", settings).ok());
  const scenes::CorridorSite site = scenes::CorridorSite::Default();
  int scoped = 0;
  for (size_t s = 0; s < kStations; ++s) {
    auto scan = scenes::MakeScanInput(site, s, scenes::LidarSettings::Small(s + 1), 1024, 2);
    ASSERT_TRUE(scan.ok()) << scan.status();
    auto r = engine->IngestScan("scoped", *scan);
    ASSERT_TRUE(r.ok()) << r.status();
    for (const auto& [stage, seconds] : r->stage_seconds) {
      if (stage.rfind("read records of", 0) != 0) continue;
      std::printf("  scan %zu: %s, %lld records in the version\n", s + 1, stage.c_str(),
                  (long long)r->record_count);
      ++scoped;
    }
  }
  EXPECT_GE(scoped, 2);  // the later scans, once the version outgrew the budget
  auto a = store::ProjectStore::Open(*dir_ / "site");
  auto b = store::ProjectStore::Open(*dir_ / "scoped");
  ASSERT_TRUE(a.ok() && b.ok());
  auto ma = (*a)->LoadManifest(int64_t(kStations));
  auto mb = (*b)->LoadManifest(int64_t(kStations));
  ASSERT_TRUE(ma.ok() && mb.ok());
  ASSERT_EQ(ma->tiles.size(), mb->tiles.size());
  int64_t objects = 0, differ = 0;
  for (const auto& [key, layers] : ma->tiles) {
    auto other = mb->tiles.find(key);
    ASSERT_NE(other, mb->tiles.end()) << tiles::ToString(key);
    for (const char* layer : {store::kLayerGeometry, store::kLayerRecords,
                              store::kLayerFusedDefault}) {
      ++objects;
      differ += layers.at(layer).object != other->second.at(layer).object ? 1 : 0;
    }
  }
  for (const auto& [source, entry] : ma->reach) {
    ++objects;
    differ += mb->reach.count(source) == 0 || mb->reach.at(source).object != entry.object;
  }
  std::printf("  %lld objects compared, %lld differ\n", (long long)objects, (long long)differ);
  EXPECT_EQ(differ, 0);
  int64_t whole_records = -1;  // what the catalog counts for version 6 of the whole ingest
  for (const store::VersionInfo& v : *(*a)->ListVersions()) {
    if (v.version == int64_t(kStations)) whole_records = v.record_count;
  }
  EXPECT_EQ((*b)->HeadInfo()->record_count, whole_records);

  // A back-projection (§10) within the budget joins as a scan does: the same image into both
  // projects gives the same records and fused objects.
  const BackProjectInput in = Retouch();
  ASSERT_FALSE(in.image.empty());
  auto into_whole = Open(false)->BackProject("site", in);
  auto into_scoped = engine->BackProject("scoped", in);
  ASSERT_TRUE(into_whole.ok()) << into_whole.status();
  ASSERT_TRUE(into_scoped.ok()) << into_scoped.status();
  EXPECT_GT(into_scoped->pixels_back_projected, int64_t(kPanoW) * kPanoH / 2);
  EXPECT_EQ(into_scoped->record_count, into_whole->record_count);
  a = store::ProjectStore::Open(*dir_ / "site");  // their HEADs moved on
  b = store::ProjectStore::Open(*dir_ / "scoped");
  ASSERT_TRUE(a.ok() && b.ok());
  auto wa = (*a)->LoadManifest(into_whole->version);
  auto wb = (*b)->LoadManifest(into_scoped->version);
  ASSERT_TRUE(wa.ok() && wb.ok());
  int64_t back_differ = 0;
  for (const auto& [key, layers] : wa->tiles) {
    for (const char* layer : {store::kLayerRecords, store::kLayerFusedDefault}) {
      back_differ += wb->tiles.at(key).at(layer).object != layers.at(layer).object ? 1 : 0;
    }
  }
  std::printf("  back-projection of %lld pixels: %lld record and fused objects differ\n",
              (long long)into_scoped->pixels_back_projected, (long long)back_differ);
  EXPECT_EQ(back_differ, 0);

  // A deletion within the budget finds the tiles its sources recorded on and rewrites them as
  // a deletion holding the whole version does: the same geometry, records, fused and reach.
  auto scans = engine->ListScans("scoped");
  ASSERT_TRUE(scans.ok() && scans->size() > 3);
  const std::string gone = (*scans)[2].name;
  auto del_whole = Open(false)->DeleteScan("site", gone);
  auto del_scoped = engine->DeleteScan("scoped", gone);
  ASSERT_TRUE(del_whole.ok()) << del_whole.status();
  ASSERT_TRUE(del_scoped.ok()) << del_scoped.status();
  for (const auto& [stage, seconds] : del_scoped->stage_seconds) {
    if (stage.rfind("read records of", 0) == 0) std::printf("  deletion: %s\n", stage.c_str());
  }
  EXPECT_EQ(del_scoped->record_count, del_whole->record_count);
  a = store::ProjectStore::Open(*dir_ / "site");
  b = store::ProjectStore::Open(*dir_ / "scoped");
  ASSERT_TRUE(a.ok() && b.ok());
  auto da = (*a)->LoadManifest(del_whole->version);
  auto db = (*b)->LoadManifest(del_scoped->version);
  ASSERT_TRUE(da.ok() && db.ok());
  ASSERT_EQ(da->tiles.size(), db->tiles.size());
  int64_t del_differ = 0;
  for (const auto& [key, layers] : da->tiles) {
    for (const char* layer : {store::kLayerGeometry, store::kLayerRecords,
                              store::kLayerFusedDefault}) {
      del_differ += db->tiles.at(key).at(layer).object != layers.at(layer).object ? 1 : 0;
    }
  }
  for (const auto& [source, entry] : da->reach) {
    del_differ += db->reach.count(source) == 0 || db->reach.at(source).object != entry.object;
  }
  std::printf("  deletion of %s: %lld records left, %lld objects differ\n", gone.c_str(),
              (long long)del_scoped->record_count, (long long)del_differ);
  EXPECT_EQ(del_differ, 0);
}

// Claim: a rebuild of a version larger than the budget makes its tiles in groups within it, one
// after another, and commits the objects a rebuild holding the whole version writes: every
// tile's geometry, records and fused layers (the default's and the reweighted profile's) and
// every reach raster; and both are the incremental version they remake, object for object.
TEST_F(BoundedReadTest, RebuildWithinTheBudgetIsTheWholeOne) {
  // A derived source too (§10): a render back-projected, whose records a rebuild re-derives.
  const BackProjectInput in = Retouch();
  ASSERT_FALSE(in.image.empty());
  auto derived = Open(false)->BackProject("site", in);
  ASSERT_TRUE(derived.ok()) << derived.status();
  ASSERT_GT(derived->pixels_back_projected, 0);

  auto before = store::ProjectStore::Open(*dir_ / "site");
  ASSERT_TRUE(before.ok()) << before.status();
  const int64_t incremental = (*before)->head_version();
  auto whole = Open(false)->Rebuild("site");
  ASSERT_TRUE(whole.ok()) << whole.status();
  auto bounded = Open(true)->Rebuild("site");
  ASSERT_TRUE(bounded.ok()) << bounded.status();
  int groups = 0, whole_groups = 0;
  for (const auto& [stage, seconds] : bounded->stage_seconds) {
    const size_t at = stage.find(" in tile group ");
    if (at != std::string::npos) groups = std::max(groups, std::atoi(stage.c_str() + at + 15));
  }
  for (const auto& [stage, seconds] : whole->stage_seconds) {
    whole_groups += stage.find(" in tile group ") != std::string::npos ? 1 : 0;
  }
  EXPECT_EQ(whole_groups, 0);
  EXPECT_GE(groups, 3) << "a fifth of the version's estimate takes several groups";
  EXPECT_EQ(bounded->record_count, whole->record_count);
  EXPECT_EQ(bounded->vossel_count, whole->vossel_count);

  auto st = store::ProjectStore::Open(*dir_ / "site");
  ASSERT_TRUE(st.ok()) << st.status();
  auto mi = (*st)->LoadManifest(incremental);
  auto mw = (*st)->LoadManifest(whole->version);
  auto mb = (*st)->LoadManifest(bounded->version);
  ASSERT_TRUE(mi.ok() && mw.ok() && mb.ok());
  int64_t objects = 0, differ = 0, from_incremental = 0;
  for (const auto& [key, layers] : mw->tiles) {
    for (const auto& [layer, entry] : layers) {
      ++objects;
      auto other = mb->tiles.find(key);
      differ += other == mb->tiles.end() || !other->second.count(layer) ||
                other->second.at(layer).object != entry.object;
      auto inc = mi->tiles.find(key);
      from_incremental += inc == mi->tiles.end() || !inc->second.count(layer) ||
                          inc->second.at(layer).object != entry.object;
    }
  }
  for (const auto& [source, entry] : mw->reach) {
    ++objects;
    differ += mb->reach.count(source) == 0 || mb->reach.at(source).object != entry.object;
  }
  std::printf("  rebuild in %d tile groups: %lld objects compared with the whole rebuild, %lld "
              "differ; %lld tile objects differ from the incremental version\n", groups,
              (long long)objects, (long long)differ, (long long)from_incremental);
  EXPECT_EQ(mb->tiles.size(), mw->tiles.size());
  EXPECT_EQ(mb->reach.size(), mw->reach.size());
  EXPECT_GT(objects, 3 * tiles_);
  EXPECT_EQ(differ, 0);
  EXPECT_EQ(from_incremental, 0);
}

// Claim: a records query reads the tiles its box meets, group by group, and answers as a
// query of the whole version: the same rows in the same order, counts and truncation.
TEST_F(BoundedReadTest, RecordsQueryIsTheWholeOne) {
  struct Box {
    Eigen::Vector3d min_m, max_m;
    int64_t limit;
  };
  const scenes::CorridorSite site = scenes::CorridorSite::Default();
  const Eigen::Vector3d o = site.Stations()[0].o_world;
  const std::vector<Box> boxes = {
      {o - Eigen::Vector3d(4, 4, 2), o + Eigen::Vector3d(4, 4, 2), 1'000'000},  // many tiles
      {o - Eigen::Vector3d(4, 4, 2), o + Eigen::Vector3d(4, 4, 2), 5000},       // truncated
      {o - Eigen::Vector3d(20, 20, 5), o + Eigen::Vector3d(20, 20, 5), 100},
  };
  auto whole_engine = Open(false);
  auto bounded_engine = Open(true);
  for (const Box& b : boxes) {
    auto whole = whole_engine->QueryRecords("site", 0, b.min_m, b.max_m, "kept", b.limit);
    auto bounded = bounded_engine->QueryRecords("site", 0, b.min_m, b.max_m, "kept", b.limit);
    ASSERT_TRUE(whole.ok()) << whole.status();
    ASSERT_TRUE(bounded.ok()) << bounded.status();
    std::printf("  query of %lld: %lld vossels, %zu rows, truncated %d\n", (long long)b.limit,
                (long long)whole->vossels, whole->rows.size(), int(whole->truncated));
    EXPECT_GT(whole->rows.size(), 50u);
    EXPECT_EQ(bounded->vossels, whole->vossels);
    EXPECT_EQ(bounded->truncated, whole->truncated);
    ASSERT_EQ(bounded->rows.size(), whole->rows.size());
    size_t differ = 0;
    for (size_t i = 0; i < whole->rows.size(); ++i) {
      const flows::RecordRow &a = whole->rows[i], &c = bounded->rows[i];
      differ += (a.vossel != c.vossel || a.coord != c.coord || a.source != c.source ||
                 a.centroid_m != c.centroid_m || a.value != c.value || a.range_m != c.range_m ||
                 a.vis != c.vis || a.conf != c.conf || a.weight != c.weight ||
                 a.scan_name != c.scan_name)
                    ? 1
                    : 0;
    }
    EXPECT_EQ(differ, 0u);
  }
  EXPECT_TRUE(absl::IsInvalidArgument(
      bounded_engine->QueryRecords("site", 0, o, o - Eigen::Vector3d(1, 0, 0), "", 10).status()));
}

}  // namespace
}  // namespace vasl

// Renders of the second synthetic site (issue "Renders and back-projection"): the corridor site's
// first two rooms, scanned from their six stations, rendered from each room's novel view and
// compared with the analytic scene, pixel by pixel. The site has what the room lacks: a thin
// horizontal table top a little below the cameras, occluders of several sizes, striped and
// checkered albedos with sharp edges, scanners at different heights and a door to see through.
// Four captures: h = 5 cm with a LiDAR grid finer than the vossel nearby (coarser at the far
// walls, so the scans carry their range grid), h = 2 cm with one dense enough for it, and
// h = 2 cm with a grid coarser than the vossel at the far walls, without and with its range grid.
// Two more captures scan seeded random sites (tests/scenes/random_site.h: oriented boxes, plates
// thinner than a vossel, tilted stations and novel views) at h = 5 cm with range grids.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <unistd.h>

#include "lattice/engine.h"
#include "tests/scenes/corridor_site.h"
#include "tests/scenes/random_site.h"

namespace vasl {
namespace {

constexpr int kPanoW = 1024, kPanoH = 512;
constexpr size_t kCorridorStations = 6;  // rooms 0 and 1

struct Capture {
  const char* name;
  double vossel_m;
  int azimuth_steps;  // LiDAR columns over 2π (rows: half)
  bool range_grid = false;  // the scans carry their range grid (gap fill, voxelise.h)
  double min_hit_share = 0.975;  // asserted share of seen pixels hit within one vossel
  uint64_t random_seed = 0;  // 0: the corridor's first two rooms; else RandomSite(seed, 6, 5)
};

struct ViewFigures {
  double psnr_db = 0.0;       // over pixels where truth and render both hit a surface
  double hit_share = 0.0;     // of the pixels whose true surface a station saw: hit within h
  int64_t seen_pixels = 0;    // pixels whose true surface some station saw
  int64_t colourless = 0;     // hit pixels whose vossel has no colour
  int64_t colourless_seen = 0;  // of them, pixels whose true surface a camera saw
  int64_t black = 0;          // hit pixels rendered black with colour (alpha 1, rgb 0)
};

class SiteRenderTest : public ::testing::TestWithParam<Capture> {
 protected:
  void SetUp() override {
    dir_ = std::filesystem::temp_directory_path() /
           ("vasl-site-render-" + std::to_string(::getpid()) + "-" + GetParam().name);
    std::filesystem::remove_all(dir_);
    auto engine = Engine::Open(dir_);
    ASSERT_TRUE(engine.ok()) << engine.status();
    engine_ = std::move(*engine);
    store::ProjectSettings settings;
    settings.vossel_size_m = GetParam().vossel_m;
    ASSERT_TRUE(engine_->CreateProject("site", settings).ok());
    scenes::LidarSettings lidar;
    lidar.azimuth_steps = GetParam().azimuth_steps;
    lidar.elevation_steps = GetParam().azimuth_steps / 2;
    for (size_t s = 0; s < stations_; ++s) {
      lidar.seed = uint64_t(s + 1);
      auto scan = scenes::MakeScanInput(site_, s, lidar, kPanoW, 2);
      ASSERT_TRUE(scan.ok()) << scan.status();
      if (GetParam().range_grid) scenes::SetRangeGrid(lidar, &scan->lidar);
      auto r = engine_->IngestScan("site", *scan);
      ASSERT_TRUE(r.ok()) << r.status();
    }
  }
  void TearDown() override {
    engine_.reset();
    std::filesystem::remove_all(dir_);
  }

  // Renders novel view v and measures it against the analytic scene.
  ViewFigures Measure(size_t v, render::ColourDetail detail) {
    ViewFigures f;
    const geometry::Pose pose = site_.NovelViews()[v];
    RenderRequest req;
    req.colour_detail = detail;
    req.pose = pose;
    req.width_px = kPanoW;
    req.height_px = kPanoH;
    auto image = engine_->Render("site", req);
    EXPECT_TRUE(image.ok()) << image.status();
    if (!image.ok()) return f;
    const scenes::Panorama truth = scenes::RenderPanorama(site_, pose, kPanoW, kPanoH, 4);
    const double h = GetParam().vossel_m;
    std::vector<bool> both(size_t(kPanoW) * kPanoH, false);
    int64_t hit_right = 0;
    for (int j = 0; j < kPanoH; ++j) {
      for (int i = 0; i < kPanoW; ++i) {
        const size_t p = size_t(j) * kPanoW + i;
        const bool hit = std::isfinite(image->depth_m[p]);
        if (hit && image->alpha[p] == 0.0f) ++f.colourless;
        if (hit && image->alpha[p] > 0.0f && image->rgb[3 * p] == 0.0f &&
            image->rgb[3 * p + 1] == 0.0f && image->rgb[3 * p + 2] == 0.0f) {
          ++f.black;
        }
        if (!std::isfinite(truth.depth_m[p])) continue;
        both[p] = hit && image->alpha[p] > 0.0f;
        // The true surface point of this pixel, and whether any station saw it.
        const Eigen::Vector3d d =
            pose.q_world_sensor * geometry::EquirectUnproject(i + 0.5, j + 0.5, {kPanoW, kPanoH});
        const Eigen::Vector3d x = pose.o_world + double(truth.depth_m[p]) * d;
        bool seen = false;
        for (size_t s = 0; s < stations_ && !seen; ++s) {
          seen = site_.Visible(site_.Stations()[s].o_world, x - 0.01 * d);
        }
        if (!seen) continue;
        ++f.seen_pixels;
        bool camera_saw = false;
        for (size_t s = 0; s < stations_ && !camera_saw; ++s) {
          camera_saw = site_.Visible(cameras_[s], x - 0.01 * d);
        }
        if (hit && image->alpha[p] == 0.0f && camera_saw) ++f.colourless_seen;
        hit_right += hit && std::abs(image->depth_m[p] - truth.depth_m[p]) < h;
      }
    }
    f.psnr_db = scenes::PsnrOver(image->rgb, truth.rgb, both);
    f.hit_share = double(hit_right) / double(std::max<int64_t>(1, f.seen_pixels));
    return f;
  }

  const scenes::CorridorSite corridor_ = scenes::CorridorSite::Default();
  const std::optional<scenes::RandomSite> random_ =
      GetParam().random_seed == 0
          ? std::nullopt
          : std::optional<scenes::RandomSite>(std::in_place, GetParam().random_seed, 6, 5);
  const scenes::Scene& site_ =
      random_ ? static_cast<const scenes::Scene&>(*random_) : corridor_;
  const size_t stations_ = random_ ? site_.Stations().size() : kCorridorStations;
  std::vector<Eigen::Vector3d> cameras_ = [this] {
    std::vector<Eigen::Vector3d> out;
    for (const geometry::Pose& s : site_.Stations()) {
      out.push_back(scenes::CameraPoseForStation(s).o_world);
    }
    return out;
  }();
  std::filesystem::path dir_;
  std::unique_ptr<Engine> engine_;
};

// Claims (§5, §8), measured against the analytic site from each room's novel view:
// - no hit pixel renders black for lack of colour (colourless vossels get alpha 0);
// - a surface that a camera saw gets colour: at most 1% of the pixels whose true surface some
//   camera saw show a colourless vossel (a camera's visibility test reads its dilated depth
//   panorama; before the slope-scaled tolerance covered the dilation, a floor or table top seen
//   at grazing incidence shadowed itself: 1.5% of novel view 1 and 3.9% of view 2 at h = 2 cm);
// - ≥ 97.5% of the pixels whose true surface a station saw hit it within one vossel, with a LiDAR
//   grid finer or coarser than the vossel; ≥ 99% when the scans carry their range grid, whose
//   gap fill closes the far floors rays passed through (2 cm, view 2: 97.57% → 99.17%), and each
//   vossel's plane is clipped to the patch its points cover (render.cc WithinPointExtent: at
//   5 cm, 98.5% → 99.0%);
// - with colour from the source images (ColourDetail::kSourceImages: each record's colour read
//   again where the pixel's own point projects into its camera), PSNR ≥ 28 dB at h = 5 cm and
//   ≥ 30 dB at h = 2 cm, the goals;
// - with one colour per vossel (the default), PSNR ≥ 20.5 dB at h = 5 cm and ≥ 25 dB at 2 cm.
//   That is the bound of one colour per vossel: the site's checker and stripe edges fall
//   mid-vossel, so each edge leaves a band one vossel wide at the mean of its two colours (an
//   oracle giving every vossel the exact mean of the true colours it shows reaches 21.7 dB on
//   novel view 1 at h = 5 cm, where the render reaches 21.0 dB).
// The hit goal is 99% of seen pixels; the printed figures say where each capture stands. The
// misses are silhouettes (a vossel overhangs its surface's edge by up to h/2) and rays through
// the gaps of a coarse grid. A random site's boxes stand at every angle, so their edges cross
// more pixels obliquely, and a plate thinner than h seen edge on renders one vossel thick: it
// asserts 98.5% (seed 3, novel view 1: 98.96%, its misses along box edges and an edge-on plate).
TEST_P(SiteRenderTest, NovelViewsMatchTheAnalyticSite) {
  const Capture& c = GetParam();
  for (size_t v = 0; v < 2; ++v) {
    const ViewFigures d = Measure(v, render::ColourDetail::kSourceImages);
    std::printf("%s, novel view %zu with colour from the source images: PSNR %.2f dB (goal "
                "%.0f); %lld black\n",
                c.name, v + 1, d.psnr_db, c.vossel_m > 0.03 ? 28.0 : 30.0, (long long)d.black);
    EXPECT_GE(d.psnr_db, c.vossel_m > 0.03 ? 28.0 : 30.0);
    EXPECT_EQ(d.black, 0);
    const ViewFigures f = Measure(v, render::ColourDetail::kVossel);
    const double colourless_share = double(f.colourless_seen) / double(f.seen_pixels);
    std::printf("%s, novel view %zu: PSNR %.2f dB (goal %.0f); %.3f%% of %lld seen pixels hit "
                "within one vossel (goal 99%%); %lld colourless pixels, %lld (%.3f%%) where a "
                "camera saw the surface; %lld black\n",
                c.name, v + 1, f.psnr_db, c.vossel_m > 0.03 ? 28.0 : 30.0, 100.0 * f.hit_share,
                (long long)f.seen_pixels, (long long)f.colourless, (long long)f.colourless_seen,
                100.0 * colourless_share, (long long)f.black);
    EXPECT_EQ(f.black, 0);
    EXPECT_LE(colourless_share, 0.01);
    EXPECT_GE(f.hit_share, c.min_hit_share);
    EXPECT_GE(f.psnr_db, c.vossel_m > 0.03 ? 20.5 : 25.0);
  }
}

void PrintTo(const Capture& c, std::ostream* os) { *os << c.name; }

INSTANTIATE_TEST_SUITE_P(
    Captures, SiteRenderTest,
    ::testing::Values(Capture{"h5cm_fine_lidar_grid", 0.05, 1440, true, 0.99},
                      Capture{"h2cm_dense_lidar", 0.02, 3600},
                      Capture{"h2cm_coarse_lidar", 0.02, 1440},
                      Capture{"h2cm_coarse_lidar_grid", 0.02, 1440, true, 0.99},
                      Capture{"random1_h5cm_grid", 0.05, 1440, true, 0.985, 1},
                      Capture{"random3_h5cm_grid", 0.05, 1440, true, 0.985, 3}),
    [](const ::testing::TestParamInfo<Capture>& info) { return std::string(info.param.name); });

}  // namespace
}  // namespace vasl

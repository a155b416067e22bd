// Claims of point-colour sources (a scan's per-point colour, as E57 files carry it): the colour
// of a LiDAR's returns becomes RGB records of a source of its own, on exactly the vossels and
// with exactly the geometry and visibility of that LiDAR's records, each record the mean colour
// of the returns in its vossel; a project of coloured scans without any panorama renders its
// colours from a new viewpoint.
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <map>
#include <tuple>

#include <gtest/gtest.h>

#include "lattice/engine.h"
#include "lattice/ingest/voxelise.h"
#include "lattice/store/project_store.h"
#include "tests/scenes/synthetic_scene.h"

namespace vasl {
namespace {
namespace fs = std::filesystem;

constexpr double kVosselM = 0.05;
constexpr int kViewW = 512, kViewH = 256;

class PointColourTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new fs::path(fs::temp_directory_path() /
                        ("vasl-point-colour-test-" + std::to_string(::getpid())));
    fs::remove_all(*dir_);
    auto engine = Engine::Open(*dir_);
    ASSERT_TRUE(engine.ok()) << engine.status();
    engine_ = engine->release();
    store::ProjectSettings settings;
    settings.vossel_size_m = kVosselM;
    ASSERT_TRUE(engine_->CreateProject("room", settings).ok());
    room_ = new scenes::SyntheticRoom(scenes::SyntheticRoom::Default());
    for (size_t i = 0; i < room_->Stations().size(); ++i) {
      // LiDAR only, each point coloured with the albedo it hit.
      auto scan = scenes::MakeScanInput(*room_, i, scenes::LidarSettings::Small(i + 1), 0, 1, true);
      ASSERT_TRUE(scan.ok()) << scan.status();
      scans_.push_back(std::move(*scan));
      auto r = engine_->IngestScan("room", scans_.back());
      ASSERT_TRUE(r.ok()) << r.status();
      std::printf("ingest %s: v%lld, %lld vossels, %lld records, %lld sources computed\n",
                  scans_.back().scan_name.c_str(), (long long)r->version,
                  (long long)r->vossel_count, (long long)r->record_count,
                  (long long)r->sources_computed);
    }
  }
  static void TearDownTestSuite() {
    delete engine_;
    fs::remove_all(*dir_);
    delete dir_;
    delete room_;
    scans_.clear();
  }
  static inline fs::path* dir_ = nullptr;
  static inline Engine* engine_ = nullptr;
  static inline scenes::SyntheticRoom* room_ = nullptr;
  static inline std::vector<ingest::ScanInput> scans_;
};

// Claim: each scan's colour is a source of its own (modality RGB, after its LiDAR), whose
// records lie on exactly the vossels of its LiDAR's records with the same range, incidence,
// footprint, pixel coordinates and visibility (§3, §5: one scanner, one depth panorama), and
// whose sample is the mean colour of the scan's returns in the vossel (within the record
// codec's rounding: 2⁻¹⁰ relative).
TEST_F(PointColourTest, ColourRecordsAreTheLidarRecordsWithTheReturnsMeanColour) {
  auto st = store::ProjectStore::Open(*dir_ / "room");
  ASSERT_TRUE(st.ok()) << st.status();
  auto snap = (*st)->LoadSnapshot((*st)->head_version());
  ASSERT_TRUE(snap.ok()) << snap.status();
  const records::VosselGeometry& g = (*snap)->geometry;
  const records::RecordSet& rec = (*snap)->records;
  auto scans = (*st)->ListScans();
  ASSERT_TRUE(scans.ok()) << scans.status();
  ASSERT_EQ(scans->size(), scans_.size());
  for (size_t s = 0; s < scans->size(); ++s) {
    const store::ScanInfo& info = (*scans)[s];
    ASSERT_EQ(info.sources.size(), 2u) << "a LiDAR and its point colour";
    const int32_t lidar_id = info.sources[0].id, colour_id = info.sources[1].id;
    EXPECT_EQ(info.sources[0].modality, records::Modality::kLidar);
    EXPECT_EQ(info.sources[1].modality, records::Modality::kRgb);
    EXPECT_EQ(info.sources[1].name, "point-colour");
    // The truth: the mean colour of the scan's returns per vossel (§1's binning).
    std::map<std::tuple<int, int, int>, std::pair<Eigen::Vector3d, int>> mean;
    const ingest::LidarData& lidar = scans_[s].lidar;
    const Eigen::Matrix3d R = scans_[s].pose.q_world_sensor.toRotationMatrix();
    for (size_t i = 0; i < lidar.xyz_sensor_m.size() / 3; ++i) {
      const Eigen::Vector3d k = ingest::VosselIndexOf(
          ingest::ReturnPosition(R, scans_[s].pose.o_world, &lidar.xyz_sensor_m[3 * i]), kVosselM);
      auto [it, fresh] = mean.try_emplace({int(k.x()), int(k.y()), int(k.z())},
                                          Eigen::Vector3d::Zero(), 0);
      auto& m = it->second;
      m.first += Eigen::Vector3d(lidar.rgb[3 * i], lidar.rgb[3 * i + 1], lidar.rgb[3 * i + 2]);
      ++m.second;
    }
    std::map<int32_t, size_t> lidar_at, colour_at;  // vossel → record
    for (size_t i = 0; i < rec.size(); ++i) {
      if (rec.scan[i] == lidar_id) lidar_at[rec.vossel[i]] = i;
      if (rec.scan[i] == colour_id) colour_at[rec.vossel[i]] = i;
    }
    ASSERT_GT(colour_at.size(), 10000u);
    EXPECT_EQ(colour_at.size(), lidar_at.size());
    size_t same_geometry = 0;
    double worst_colour = 0.0;
    for (const auto& [v, i] : colour_at) {
      auto l = lidar_at.find(v);
      ASSERT_NE(l, lidar_at.end()) << "a colour record on a vossel without the LiDAR's record";
      const size_t j = l->second;
      EXPECT_EQ(rec.modality[i], int8_t(records::Modality::kRgb));
      same_geometry += rec.range_m[i] == rec.range_m[j] && rec.cos_inc[i] == rec.cos_inc[j] &&
                       rec.foot_major_m[i] == rec.foot_major_m[j] &&
                       rec.foot_minor_m[i] == rec.foot_minor_m[j] &&
                       rec.uv_px[2 * i] == rec.uv_px[2 * j] &&
                       rec.uv_px[2 * i + 1] == rec.uv_px[2 * j + 1] && rec.vis[i] == rec.vis[j];
      const openvdb::Coord c = g.coord[size_t(v)];
      const auto& m = mean.at({c.x(), c.y(), c.z()});
      for (int ch = 0; ch < 3; ++ch) {
        const double truth = m.first[ch] / m.second;
        worst_colour = std::max(worst_colour, std::abs(rec.value[3 * i + ch] - truth) / truth);
      }
    }
    std::printf("%s: %zu colour records on the %zu vossels of its LiDAR's, %zu with the same "
                "geometry and visibility; worst relative colour error %.2g\n",
                info.name.c_str(), colour_at.size(), lidar_at.size(), same_geometry, worst_colour);
    EXPECT_EQ(same_geometry, colour_at.size());
    EXPECT_LE(worst_colour, 1.0 / 1024.0);
  }
}

// Claim (§7, §8): a project whose colour comes from its scans' points alone (no panorama)
// renders the site's colours from a viewpoint no scanner stood at: PSNR ≥ 25 dB against the
// analytic scene over the pixels that hit and have colour, and ≥ 99% of them have colour.
TEST_F(PointColourTest, ColouredScansAloneRenderTheSite) {
  for (size_t v = 0; v < room_->NovelViews().size(); ++v) {
    RenderRequest req;
    req.pose = room_->NovelViews()[v];
    req.width_px = kViewW;
    req.height_px = kViewH;
    auto image = engine_->Render("room", req);
    ASSERT_TRUE(image.ok()) << image.status();
    const scenes::Panorama truth = scenes::RenderPanorama(*room_, req.pose, kViewW, kViewH, 4);
    double se = 0.0;
    size_t hits = 0, coloured = 0;
    for (size_t p = 0; p < size_t(kViewW) * kViewH; ++p) {
      if (!std::isfinite(image->depth_m[p]) || !std::isfinite(truth.depth_m[p])) continue;
      ++hits;
      if (!(image->alpha[p] > 0.0f)) continue;
      ++coloured;
      for (int c = 0; c < 3; ++c) {
        const double d = double(image->rgb[3 * p + c]) - truth.rgb[3 * p + c];
        se += d * d;
      }
    }
    const double psnr = 10.0 * std::log10(3.0 * double(coloured) / se);
    std::printf("novel view %zu from point colours alone: PSNR %.2f dB over %zu coloured of %zu "
                "hit pixels\n", v + 1, psnr, coloured, hits);
    EXPECT_GE(psnr, 25.0);
    EXPECT_GE(double(coloured) / double(hits), 0.99);
  }
}

}  // namespace
}  // namespace vasl

// The whole path on real parts, without the network: ingest the synthetic room's scans into a
// store on disk, render (VASL-MODEL §8) and compare with the analytic scene; bad input leaves
// the project unchanged.
#include "lattice/engine.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include <gtest/gtest.h>

#include "lattice/ingest/sources.h"
#include "lattice/store/project_store.h"
#include "tests/scenes/synthetic_scene.h"

namespace vasl {
namespace {

constexpr double kVosselM = 0.05;
constexpr int kPanoW = 1024, kPanoH = 512;

class EngineTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new std::filesystem::path(std::filesystem::temp_directory_path() /
                                     ("vasl-engine-test-" + std::to_string(::getpid())));
    std::filesystem::remove_all(*dir_);
    auto engine = Engine::Open(*dir_);
    ASSERT_TRUE(engine.ok()) << engine.status();
    engine_ = engine->release();
    store::ProjectSettings settings;
    settings.vossel_size_m = kVosselM;
    ASSERT_TRUE(engine_->CreateProject("room", settings).ok());
    room_ = new scenes::SyntheticRoom(scenes::SyntheticRoom::Default());
    scenes::LidarSettings lidar;
    lidar.azimuth_steps = 1440;
    lidar.elevation_steps = 720;
    for (size_t i = 0; i < room_->Stations().size(); ++i) {
      lidar.seed = uint64_t(i + 1);
      auto scan = scenes::MakeScanInput(*room_, i, lidar, kPanoW);
      ASSERT_TRUE(scan.ok()) << scan.status();
      auto result = engine_->IngestScan("room", *scan);
      ASSERT_TRUE(result.ok()) << result.status();
      std::printf("ingest %s: version %lld, %lld vossels (+%lld), %lld records, %.2f s:",
                  scan->scan_name.c_str(), (long long)result->version, (long long)result->vossel_count,
                  (long long)result->new_vossels, (long long)result->record_count, result->seconds);
      for (const auto& [stage, s] : result->stage_seconds) std::printf(" %s %.2f", stage.c_str(), s);
      std::printf("\n");
      pngs_.push_back(scan->panoramas[0].encoded_image);
    }
  }
  static void TearDownTestSuite() {
    delete engine_;
    delete room_;
    std::filesystem::remove_all(*dir_);
    delete dir_;
  }

  static std::filesystem::path* dir_;
  static Engine* engine_;
  static scenes::SyntheticRoom* room_;
  static std::vector<std::string> pngs_;
};
std::filesystem::path* EngineTest::dir_ = nullptr;
Engine* EngineTest::engine_ = nullptr;
scenes::SyntheticRoom* EngineTest::room_ = nullptr;
std::vector<std::string> EngineTest::pngs_;

// Claim (§8): a render from a station camera's own pose reproduces its panorama, PSNR ≥ 30 dB
// over hit pixels.
TEST_F(EngineTest, RenderFromStationReproducesItsPanorama) {
  for (size_t s = 0; s < room_->Stations().size(); ++s) {
    RenderRequest req;
    req.pose = scenes::CameraPoseForStation(room_->Stations()[s]);
    req.width_px = kPanoW;
    req.height_px = kPanoH;
    auto image = engine_->Render("room", req);
    ASSERT_TRUE(image.ok()) << image.status();
    auto input = ingest::DecodeImage(pngs_[s], false, int64_t(1) << 30);
    ASSERT_TRUE(input.ok());
    std::vector<bool> hit(size_t(kPanoW) * kPanoH);
    for (size_t p = 0; p < hit.size(); ++p) hit[p] = std::isfinite(image->depth_m[p]);
    const double psnr = scenes::PsnrOver(image->rgb, input->pixels, hit);
    std::printf("station %zu camera: render vs its own panorama PSNR %.2f dB over %lld hit pixels "
                "(%.2f%% of the image)\n", s + 1, psnr, (long long)image->hit_pixels,
                100.0 * image->hit_pixels / hit.size());
    EXPECT_GE(psnr, 30.0);
    EXPECT_GT(image->hit_pixels, int64_t(hit.size() * 0.97)) << "inside a closed room nearly every ray hits";
  }
}

// Claim (§8): from a new viewpoint the render matches the analytic scene: PSNR ≥ 25 dB, and the
// depth error is below one vossel for ≥ 95% of hit pixels.
TEST_F(EngineTest, RenderFromNovelViewMatchesAnalyticScene) {
  for (size_t v = 0; v < room_->NovelViews().size(); ++v) {
    const geometry::Pose pose = room_->NovelViews()[v];
    RenderRequest req;
    req.pose = pose;
    req.width_px = kPanoW;
    req.height_px = kPanoH;
    auto image = engine_->Render("room", req);
    ASSERT_TRUE(image.ok()) << image.status();
    const scenes::Panorama truth = scenes::RenderPanorama(*room_, pose, kPanoW, kPanoH, 4);
    std::vector<bool> hit(size_t(kPanoW) * kPanoH);
    size_t hits = 0, depth_ok = 0;
    for (size_t p = 0; p < hit.size(); ++p) {
      hit[p] = std::isfinite(image->depth_m[p]) && std::isfinite(truth.depth_m[p]);
      if (!hit[p]) continue;
      ++hits;
      depth_ok += std::abs(image->depth_m[p] - truth.depth_m[p]) < kVosselM;
    }
    const double psnr = scenes::PsnrOver(image->rgb, truth.rgb, hit);
    std::printf("novel view %zu: PSNR %.2f dB vs analytic scene; depth error < 1 vossel for %.2f%% "
                "of %zu hit pixels\n", v + 1, psnr, 100.0 * depth_ok / hits, hits);
    EXPECT_GE(psnr, 25.0);
    EXPECT_GE(double(depth_ok) / hits, 0.95);
  }
}

// Claim (§5, §7): no record carries the occluder's colour onto the surface behind it. Every wall
// vossel's fused colour matches the analytic albedo at its centroid, including along the edges
// of the box's shadows (a camera sample reads a neighbourhood of pixels, so visibility must
// cover that neighbourhood: DilateDepthPanorama).
TEST_F(EngineTest, FusedColourMatchesAlbedoAlongShadowEdges) {
  auto st = store::ProjectStore::Open(*dir_ / "room");
  ASSERT_TRUE(st.ok()) << st.status();
  auto snap = (*st)->LoadSnapshot((*st)->head_version());
  ASSERT_TRUE(snap.ok()) << snap.status();
  const records::VosselGeometry& g = (*snap)->geometry;
  const records::FusedModality& rgb = (*snap)->fused.by_modality.at(records::Modality::kRgb);
  const scenes::Aabb& room = room_->RoomBounds();
  std::vector<double> errors;
  for (size_t k = 0; k < g.size(); ++k) {
    Eigen::Vector3d x = g.centroid_m[k].cast<double>();
    int face = -1;
    if (std::abs(x.y() - room.max_m.y()) < 0.01) face = scenes::kFaceWallYMax;
    if (std::abs(x.x() - room.max_m.x()) < 0.01) face = scenes::kFaceWallXMax;
    if (std::abs(x.x() - room.min_m.x()) < 0.01) face = scenes::kFaceWallXMin;
    if (face < 0 || rgb.weight[k] <= 0.0f) continue;
    if (x.z() < 0.1 || x.z() > room.max_m.z() - 0.1) continue;  // not the room's edges
    const int along = face == scenes::kFaceWallYMax ? 0 : 1;  // the wall's horizontal axis
    if (x[along] < room.min_m[along] + 0.1 || x[along] > room.max_m[along] - 0.1) continue;
    const Eigen::Vector3f a = room_->Albedo(x, face);
    double e = 0.0;
    for (int c = 0; c < 3; ++c) e = std::max(e, double(std::abs(rgb.value[3 * k + c] - a[c])));
    errors.push_back(e);
  }
  ASSERT_GT(errors.size(), 10000u);
  std::sort(errors.begin(), errors.end());
  const double p999 = errors[errors.size() * 999 / 1000], worst = errors.back();
  std::printf("wall vossels: fused colour vs albedo, %zu vossels: median %.4f, 99.9%% %.4f, max %.4f\n",
              errors.size(), errors[errors.size() / 2], p999, worst);
  EXPECT_LT(worst, 0.1) << "a record carries another surface's colour";
}

// Claim (ARCHITECTURE "Errors and limits"): bad input gets a clear error and leaves the project
// unchanged (same HEAD version, same scans).
TEST_F(EngineTest, BadInputLeavesProjectUnchanged) {
  auto before = engine_->GetProject("room");
  ASSERT_TRUE(before.ok());
  ScanInput good;
  good.scan_name = "bad-input";
  good.pose = room_->Stations()[0];
  good.lidar.xyz_sensor_m = {1.0f, 0.0f, 0.0f, 0.0f, 2.0f, 0.0f};

  ScanInput nan_pose = good;
  nan_pose.pose.o_world.x() = std::numeric_limits<double>::quiet_NaN();
  EXPECT_EQ(engine_->IngestScan("room", nan_pose).status().code(), absl::StatusCode::kInvalidArgument);

  ScanInput bad_image = good;
  PanoramaData pano;
  pano.name = "cam0";
  pano.pose = good.pose;
  pano.encoded_image = "\x89PNG but not really an image";
  bad_image.panoramas.push_back(pano);
  auto st = engine_->IngestScan("room", bad_image).status();
  EXPECT_EQ(st.code(), absl::StatusCode::kInvalidArgument);
  std::printf("undecodable image: %s\n", std::string(st.message()).c_str());

  ScanInput ragged = good;
  ragged.lidar.xyz_sensor_m.push_back(1.0f);
  EXPECT_EQ(engine_->IngestScan("room", ragged).status().code(), absl::StatusCode::kInvalidArgument);

  ScanInput no_points = good;
  no_points.lidar.xyz_sensor_m.clear();
  EXPECT_EQ(engine_->IngestScan("room", no_points).status().code(), absl::StatusCode::kInvalidArgument);

  ScanInput duplicate = good;
  duplicate.scan_name = "scan-1";
  EXPECT_EQ(engine_->IngestScan("room", duplicate).status().code(), absl::StatusCode::kAlreadyExists);

  EXPECT_EQ(engine_->IngestScan("no-such-project", good).status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(engine_->GetProject("no-such-project").status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(engine_->CreateProject("Bad Name!", {}).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(engine_->CreateProject("room", {}).status().code(), absl::StatusCode::kAlreadyExists);

  auto after = engine_->GetProject("room");
  ASSERT_TRUE(after.ok());
  EXPECT_EQ(after->head_version, before->head_version);
  EXPECT_EQ(after->scan_count, before->scan_count);
  EXPECT_EQ(after->record_count, before->record_count);
}

// Claim (ARCHITECTURE "Errors and limits"): a change sent under a request id is done once. A
// retry gets the committed version back (replayed) without a new version; the id cannot name
// another change; the record outlives the engine; without an id a duplicate scan is refused.
TEST_F(EngineTest, RetryUnderARequestIdIsAnsweredFromItsCommit) {
  const std::filesystem::path dir = *dir_ / ".." / (dir_->filename().string() + "-retry");
  std::filesystem::remove_all(dir);
  auto opened = Engine::Open(dir);  // a data directory of its own: the room stays alone
  ASSERT_TRUE(opened.ok()) << opened.status();
  Engine* engine = opened->get();
  store::ProjectSettings settings;
  settings.vossel_size_m = kVosselM;
  ASSERT_TRUE(engine->CreateProject("retry", settings).ok());
  scenes::LidarSettings lidar;
  lidar.azimuth_steps = 360;
  lidar.elevation_steps = 180;
  auto scan = scenes::MakeScanInput(*room_, 0, lidar, 256);
  ASSERT_TRUE(scan.ok()) << scan.status();
  scan->request_id = "3f2a9c1e-ingest-1";
  auto first = engine->IngestScan("retry", *scan);
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_FALSE(first->replayed);
  ASSERT_TRUE(engine->SetOperationAnswer("retry", scan->request_id, std::string("ans\0wer", 7)).ok());

  auto again = engine->IngestScan("retry", *scan);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_TRUE(again->replayed);
  EXPECT_EQ(again->version, first->version);
  EXPECT_EQ(again->scan_id, first->scan_id);
  EXPECT_EQ(again->answer, std::string("ans\0wer", 7));
  EXPECT_EQ(engine->GetProject("retry")->head_version, first->version) << "no second version";

  ScanInput other = *scan;
  other.scan_name = "another-scan";
  auto reused = engine->IngestScan("retry", other);
  EXPECT_EQ(reused.status().code(), absl::StatusCode::kFailedPrecondition) << reused.status();
  std::printf("reused id: %s\n", std::string(reused.status().message()).c_str());
  other.request_id = "not an id!";
  EXPECT_EQ(engine->IngestScan("retry", other).status().code(), absl::StatusCode::kInvalidArgument);
  ScanInput no_id = *scan;
  no_id.request_id.clear();
  EXPECT_EQ(engine->IngestScan("retry", no_id).status().code(), absl::StatusCode::kAlreadyExists);

  auto deleted = engine->DeleteScan("retry", scan->scan_name, {}, "delete-1");
  ASSERT_TRUE(deleted.ok()) << deleted.status();
  auto deleted_again = engine->DeleteScan("retry", scan->scan_name, {}, "delete-1");
  ASSERT_TRUE(deleted_again.ok()) << deleted_again.status();
  EXPECT_TRUE(deleted_again->replayed);
  EXPECT_EQ(deleted_again->version, deleted->version);
  EXPECT_EQ(engine->GetProject("retry")->head_version, deleted->version);

  auto reopened = Engine::Open(dir);
  ASSERT_TRUE(reopened.ok());
  auto found = (*reopened)->FindOperation("retry", {"3f2a9c1e-ingest-1", "", ""});
  ASSERT_TRUE(found.ok() && found->has_value()) << found.status();
  EXPECT_EQ((*found)->kind, "ingest");
  EXPECT_EQ((*found)->subject, scan->scan_name);
  EXPECT_EQ((*found)->version, first->version);
  EXPECT_EQ((*found)->answer, std::string("ans\0wer", 7));
  auto unknown = (*reopened)->FindOperation("retry", {"never-sent", "", ""});
  ASSERT_TRUE(unknown.ok());
  EXPECT_FALSE(unknown->has_value());
  opened->reset();
  reopened->reset();
  std::filesystem::remove_all(dir);
}

// Claim (ARCHITECTURE "Storage"): the project persists; a new engine on the same data dir sees
// the same HEAD, scans and records, and renders from them.
TEST_F(EngineTest, ReopenedStoreServesTheSameProject) {
  auto before = engine_->GetProject("room");
  ASSERT_TRUE(before.ok());
  auto other = Engine::Open(*dir_);
  ASSERT_TRUE(other.ok());
  auto info = (*other)->GetProject("room");
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_EQ(info->head_version, int64_t(room_->Stations().size()));
  EXPECT_EQ(info->scan_count, int64_t(room_->Stations().size()));
  EXPECT_EQ(info->vossel_count, before->vossel_count);
  EXPECT_EQ(info->record_count, before->record_count);
  auto scans = (*other)->ListScans("room");
  ASSERT_TRUE(scans.ok());
  ASSERT_EQ(scans->size(), room_->Stations().size());
  EXPECT_EQ(scans->front().sources.size(), 2u);  // LiDAR + one camera
  auto projects = (*other)->ListProjects();
  ASSERT_TRUE(projects.ok());
  ASSERT_EQ(projects->size(), 1u);
  RenderRequest req;
  req.pose = room_->NovelViews()[0];
  req.width_px = 256;
  req.height_px = 128;
  auto image = (*other)->Render("room", req);
  ASSERT_TRUE(image.ok()) << image.status();
  EXPECT_GT(image->hit_pixels, 256 * 128 * 9 / 10);
  auto attrs = (*other)->InspectRecords("room", 0);
  ASSERT_TRUE(attrs.ok()) << attrs.status();
  EXPECT_GE(attrs->attributes.size(), 11u);
  EXPECT_GE(attrs->tile_count, 1);
  EXPECT_EQ(attrs->record_count, (*other)->GetProject("room")->record_count);
}

}  // namespace
}  // namespace vasl

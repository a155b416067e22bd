// Calibration health through ingest (VASL-MODEL §2.3, issue "Real captures in"): each camera
// of a scan with LiDAR is checked against that LiDAR at ingest, the figures come back with the
// ingest's result, and the catalog keeps them with the camera, through a reopen. A station's
// panorama on its true pose is ok; a scan whose camera pose is turned by 0.5° is flagged (the
// 2048-pixel panorama puts 0.5° at 2.8 px); a camera-only scan has no LiDAR to be checked by.
#include <cstdio>
#include <filesystem>

#include <gtest/gtest.h>

#include "lattice/engine.h"
#include "tests/scenes/synthetic_scene.h"

namespace vasl {
namespace {
namespace fs = std::filesystem;

using Verdict = records::CalibrationHealth::Verdict;
constexpr double kVosselM = 0.05;
constexpr int kPanoW = 2048;
constexpr double kTurnRad = 0.5 * M_PI / 180.0;

const records::CalibrationHealth* Of(const std::vector<store::ScanInfo>& scans,
                                     const std::string& scan, const std::string& camera) {
  for (const store::ScanInfo& s : scans)
    for (const store::SourceInfo& src : s.sources)
      if (s.name == scan && src.name == camera && src.calibration) return &*src.calibration;
  return nullptr;
}

TEST(CalibrationFlowTest, IngestChecksEachCameraAndTheCatalogKeepsIt) {
  const fs::path dir = fs::temp_directory_path() / ("vasl-calib-flow-" + std::to_string(::getpid()));
  fs::remove_all(dir);
  const scenes::SyntheticRoom room = scenes::SyntheticRoom::Default();
  store::ProjectSettings settings;
  settings.vossel_size_m = kVosselM;
  {
    auto engine = Engine::Open(dir);
    ASSERT_TRUE(engine.ok()) << engine.status();
    ASSERT_TRUE((*engine)->CreateProject("p", settings).ok());
    for (size_t station : {0, 1}) {
      auto scan = scenes::MakeScanInput(room, station, scenes::LidarSettings::Small(station + 1),
                                        kPanoW);
      ASSERT_TRUE(scan.ok()) << scan.status();
      if (station == 1) {  // the rig's camera is off its pose by 0.5°
        geometry::Pose& pose = scan->panoramas[0].pose;
        pose.q_world_sensor = pose.q_world_sensor *
            Eigen::Quaterniond(Eigen::AngleAxisd(kTurnRad, Eigen::Vector3d(0.2, -0.4, 0.9).normalized()));
      }
      auto r = (*engine)->IngestScan("p", *scan);
      ASSERT_TRUE(r.ok()) << r.status();
      ASSERT_EQ(r->calibration.size(), 1u);
      const auto& [camera, h] = r->calibration[0];
      EXPECT_EQ(camera, "cam0");
      std::printf("station %zu: %s, %lld/%lld patches, pixel residual mean %.3f p95 %.3f px "
                  "(cell %.0f px), offset p95 %.1f mm, rotation %.3f deg\n",
                  station, records::VerdictName(h.verdict), static_cast<long long>(h.matched),
                  static_cast<long long>(h.features), h.pixel_mean_px, h.pixel_p95_px, h.cell_px,
                  1e3 * h.offset_p95_m, h.rotation_deg);
      EXPECT_EQ(h.verdict, station == 0 ? Verdict::kOk : Verdict::kFlagged) << h.note;
      if (station == 0) {
        EXPECT_LE(h.pixel_p95_px, 1.0);
      } else {
        EXPECT_NEAR(h.rotation_deg, 0.5, 0.05);
      }
      double seconds = 0;
      for (const auto& [stage, s] : r->stage_seconds)
        if (stage.rfind("calibration", 0) == 0) seconds += s;
      std::printf("station %zu: calibration stage %.2f s of %.2f s\n", station, seconds, r->seconds);
    }
    // A camera-only scan: no LiDAR of its own to check its camera by.
    auto photo = scenes::MakeCameraOnlyScan(room, "photos", room.NovelViews()[0],
                                            room.NovelViews()[0], 512);
    ASSERT_TRUE(photo.ok()) << photo.status();
    auto r = (*engine)->IngestScan("p", *photo);
    ASSERT_TRUE(r.ok()) << r.status();
    EXPECT_TRUE(r->calibration.empty());
  }
  auto engine = Engine::Open(dir);  // the catalog kept the figures
  ASSERT_TRUE(engine.ok()) << engine.status();
  auto scans = (*engine)->ListScans("p");
  ASSERT_TRUE(scans.ok()) << scans.status();
  const records::CalibrationHealth* good = Of(*scans, "scan-1", "cam0");
  const records::CalibrationHealth* off = Of(*scans, "scan-2", "cam0");
  ASSERT_NE(good, nullptr);
  ASSERT_NE(off, nullptr);
  EXPECT_EQ(good->verdict, Verdict::kOk);
  EXPECT_EQ(off->verdict, Verdict::kFlagged);
  EXPECT_NE(off->note.find("check the camera's pose"), std::string::npos) << off->note;
  EXPECT_GT(off->pixel_p95_px, 2.0);
  EXPECT_EQ(Of(*scans, "photos", "photo"), nullptr);
  engine->reset();
  fs::remove_all(dir);
}

}  // namespace
}  // namespace vasl

// VASL-MODEL §2.3 on the synthetic room: a camera on its true pose has round-trip and pixel
// residuals within a pixel; the same camera with its pose turned by 0.5° is flagged, and the
// rotation that best explains its residuals is the 0.5° it was turned by. For the station's
// equirect panorama (2048 × 1024: 0.5° is 2.8 px) and for a pinhole survey photo (640 × 480,
// 65° across with barrel distortion: 0.5° is about 5 px).
#include "lattice/ingest/calibration.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <random>
#include <utility>
#include <vector>

#include <gtest/gtest.h>
#include <tbb/task_arena.h>

#include "lattice/memory/isa.h"
#include "tests/scenes/synthetic_scene.h"

namespace vasl::ingest {
namespace {

using Verdict = records::CalibrationHealth::Verdict;

constexpr int kPanoWidth = 2048;
constexpr double kTurnDeg = 0.5;
// The true pose is judged within a pixel (issue "Real captures in").
constexpr double kTruePoseP95Px = 1.0;
// The fitted rotation recovers the turn within a tenth of it.
constexpr double kTurnToleranceDeg = 0.05;
// The round trip tests the projection model: float32 returns and the pinhole's iterative
// undistortion leave micrometres.
constexpr double kRoundTripM = 1e-5;

class CalibrationTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    room_ = new scenes::SyntheticRoom(scenes::SyntheticRoom::Default());
    const geometry::Pose station = room_->Stations()[0];
    scenes::LidarScan scan = scenes::GenerateLidar(*room_, station, scenes::LidarSettings{});
    lidar_ = new LidarSource;
    lidar_->id = 1;
    lidar_->pose = station;
    lidar_->xyz_sensor_m = std::move(scan.xyz_sensor_m);
    lidar_->intensity = std::move(scan.intensity);
    lidar_->rgb = std::move(scan.rgb);
  }
  static void TearDownTestSuite() {
    delete room_;
    delete lidar_;
  }

  // The camera's image as ingest decodes it: rendered, encoded as 8-bit sRGB PNG, decoded.
  static LinearImage Decoded(const scenes::Panorama& pano) {
    absl::StatusOr<std::string> png = scenes::EncodePng(pano);
    EXPECT_TRUE(png.ok()) << png.status();
    absl::StatusOr<LinearImage> image = DecodeImage(*png, false, int64_t{1} << 30);
    EXPECT_TRUE(image.ok()) << image.status();
    return *image;
  }

  // The station's panorama camera on its true pose, and its image as ingest decodes it.
  static std::pair<geometry::Pose, LinearImage> StationPanorama() {
    const geometry::Pose truth = scenes::CameraPoseForStation(lidar_->pose);
    return {truth, Decoded(scenes::RenderPanorama(*room_, truth, kPanoWidth, kPanoWidth / 2))};
  }

  // `pose` turned by kTurnDeg about an axis oblique to every camera axis.
  static geometry::Pose Turned(geometry::Pose pose) {
    const Eigen::Vector3d axis = Eigen::Vector3d(0.3, 0.5, 0.8).normalized();
    pose.q_world_sensor =
        pose.q_world_sensor * Eigen::Quaterniond(Eigen::AngleAxisd(kTurnDeg * M_PI / 180, axis));
    return pose;
  }

  static void Print(const char* what, const records::CalibrationHealth& h) {
    std::printf("%s: %s, %lld returns in view, %lld/%lld patches matched, cell %.0f px, pixel "
                "residual mean %.3f p95 %.3f px, offset mean %.2f p95 %.2f mm, round trip p95 "
                "%.2g m, rotation %.3f deg%s%s\n",
                what, records::VerdictName(h.verdict), static_cast<long long>(h.points_in_view),
                static_cast<long long>(h.matched), static_cast<long long>(h.features), h.cell_px,
                h.pixel_mean_px, h.pixel_p95_px, 1e3 * h.offset_mean_m, 1e3 * h.offset_p95_m,
                h.roundtrip_p95_m, h.rotation_deg, h.note.empty() ? "" : ": ", h.note.c_str());
  }

  static scenes::SyntheticRoom* room_;
  static LidarSource* lidar_;
};
scenes::SyntheticRoom* CalibrationTest::room_ = nullptr;
LidarSource* CalibrationTest::lidar_ = nullptr;

// Claim (§2.3): the station's panorama on its true pose matches the LiDAR within a pixel; the
// same panorama on a pose turned by 0.5° is flagged, and the fitted rotation is that 0.5°.
TEST_F(CalibrationTest, PanoramaOnItsPoseIsOkAndTurnedIsFlagged) {
  const auto [truth, image] = StationPanorama();
  CameraSource camera;
  camera.id = 2;
  camera.pose = truth;
  const records::CalibrationHealth good = CheckCalibration(*lidar_, camera, image);
  Print("panorama, true pose", good);
  EXPECT_EQ(good.verdict, Verdict::kOk) << good.note;
  EXPECT_GE(good.matched, 100);
  EXPECT_LE(good.pixel_p95_px, kTruePoseP95Px);
  EXPECT_LE(good.roundtrip_p95_m, kRoundTripM);
  EXPECT_LT(good.rotation_deg, kTurnToleranceDeg);

  camera.pose = Turned(truth);
  const records::CalibrationHealth off = CheckCalibration(*lidar_, camera, image);
  Print("panorama, pose turned 0.5 deg", off);
  EXPECT_EQ(off.verdict, Verdict::kFlagged);
  EXPECT_NEAR(off.rotation_deg, kTurnDeg, kTurnToleranceDeg);
  EXPECT_GT(off.pixel_p95_px, 2.0);
  EXPECT_LE(off.roundtrip_p95_m, kRoundTripM);  // the model itself is sound either way
}

// Claim: the same for a pinhole photo with distortion, and its round trip (iterative
// undistortion) stays within micrometres.
TEST_F(CalibrationTest, PinholePhotoOnItsPoseIsOkAndTurnedIsFlagged) {
  const geometry::PinholeIntrinsics k = scenes::SurveyPhotoIntrinsics();
  const Eigen::Vector3d o = scenes::CameraPoseForStation(lidar_->pose).o_world;
  const geometry::Pose truth = scenes::LookAt(o, room_->OccluderBounds().max_m + Eigen::Vector3d(0.5, 0.8, -0.4));
  const LinearImage image = Decoded(scenes::RenderPinhole(*room_, truth, k));
  CameraSource camera;
  camera.id = 2;
  camera.pose = truth;
  camera.pinhole = k;
  // A LiDAR as fine as the photo's pixels (0.1°), so that the check resolves single pixels.
  scenes::LidarSettings fine;
  fine.azimuth_steps = 3600;
  fine.elevation_steps = 1800;
  scenes::LidarScan scan = scenes::GenerateLidar(*room_, lidar_->pose, fine);
  LidarSource lidar;
  lidar.id = 1;
  lidar.pose = lidar_->pose;
  lidar.xyz_sensor_m = std::move(scan.xyz_sensor_m);
  lidar.intensity = std::move(scan.intensity);
  const records::CalibrationHealth good = CheckCalibration(lidar, camera, image);
  Print("pinhole, true pose", good);
  EXPECT_EQ(good.verdict, Verdict::kOk) << good.note;
  EXPECT_GE(good.matched, 20);
  EXPECT_LE(good.pixel_p95_px, kTruePoseP95Px);
  EXPECT_LE(good.roundtrip_p95_m, kRoundTripM);

  camera.pose = Turned(truth);
  const records::CalibrationHealth off = CheckCalibration(lidar, camera, image);
  Print("pinhole, pose turned 0.5 deg", off);
  EXPECT_EQ(off.verdict, Verdict::kFlagged);
  EXPECT_NEAR(off.rotation_deg, kTurnDeg, kTurnToleranceDeg);
}

// Claim: without intensity the points' colour serves; with neither, and for a camera that sees
// none of the returns, the pair is unchecked with the reason, not judged.
TEST_F(CalibrationTest, ColourServesAndNothingToMatchIsUnchecked) {
  const geometry::Pose truth = scenes::CameraPoseForStation(lidar_->pose);
  const LinearImage image =
      Decoded(scenes::RenderPanorama(*room_, truth, kPanoWidth / 2, kPanoWidth / 4));
  CameraSource camera;
  camera.id = 2;
  camera.pose = truth;
  LidarSource colour_only = *lidar_;
  colour_only.intensity.clear();
  const records::CalibrationHealth by_colour = CheckCalibration(colour_only, camera, image);
  Print("panorama 1024, colour only", by_colour);
  EXPECT_EQ(by_colour.verdict, Verdict::kOk) << by_colour.note;

  LidarSource bare = colour_only;
  bare.rgb.clear();
  const records::CalibrationHealth none = CheckCalibration(bare, camera, image);
  EXPECT_EQ(none.verdict, Verdict::kUnchecked);
  EXPECT_NE(none.note.find("neither intensity nor colour"), std::string::npos) << none.note;

  CameraSource away = camera;  // a pinhole looking at the floor from below it sees nothing
  away.pinhole = scenes::SurveyPhotoIntrinsics();
  away.pose = scenes::LookAt(truth.o_world - Eigen::Vector3d(0, 0, 10), truth.o_world + Eigen::Vector3d(0.1, 0, -20));
  const records::CalibrationHealth blind = CheckCalibration(*lidar_, away, image);
  EXPECT_EQ(blind.verdict, Verdict::kUnchecked);
  EXPECT_EQ(blind.points_in_view, 0);
}

// Claim: the figures a check stores with a source are reproducible: the same scan and image
// give the same health, to the last bit, on one thread and on several (a rebuild computes them
// again and must find what ingest stored).
TEST_F(CalibrationTest, FiguresDoNotDependOnTheThreads) {
  const std::pair<geometry::Pose, LinearImage> panorama = StationPanorama();
  const geometry::Pose& truth = panorama.first;
  const LinearImage& image = panorama.second;  // named, not bound: the lambda below reads it
  CameraSource camera;
  camera.id = 2;
  camera.pose = Turned(truth);  // matches off their projections: every figure non-zero
  const auto check = [&](int threads) {
    tbb::task_arena arena(threads);
    return arena.execute([&] { return CheckCalibration(*lidar_, camera, image); });
  };
  const records::CalibrationHealth one = check(1);
  {
    const int threads = std::max(2, tbb::this_task_arena::max_concurrency());
    const records::CalibrationHealth many = check(threads);
    SCOPED_TRACE(threads);
    EXPECT_EQ(many.points_in_view, one.points_in_view);
    EXPECT_EQ(many.features, one.features);
    EXPECT_EQ(many.matched, one.matched);
    EXPECT_EQ(many.cell_px, one.cell_px);
    EXPECT_EQ(many.pixel_mean_px, one.pixel_mean_px);
    EXPECT_EQ(many.pixel_p95_px, one.pixel_p95_px);
    EXPECT_EQ(many.offset_mean_m, one.offset_mean_m);
    EXPECT_EQ(many.offset_p95_m, one.offset_p95_m);
    EXPECT_EQ(many.roundtrip_mean_m, one.roundtrip_mean_m);
    EXPECT_EQ(many.roundtrip_p95_m, one.roundtrip_p95_m);
    EXPECT_EQ(many.rotation_deg, one.rotation_deg);
    EXPECT_EQ(many.verdict, one.verdict);
  }
  EXPECT_GT(one.pixel_mean_px, 0.0);
}

// The correlation of the template against the window at shift (dx, dy), one shift at a time:
// the sums over the pairs where both are finite, in the template's row-major order.
double OneShift(const std::vector<float>& templ, const std::vector<float>& window, int R, int S,
                int dx, int dy, size_t min_n) {
  const int patch = 2 * R + 1, span = 2 * (R + S) + 1;
  double sa = 0, sb = 0, saa = 0, sbb = 0, sab = 0;
  size_t n = 0;
  for (int j = 0; j < patch; ++j)
    for (int i = 0; i < patch; ++i) {
      const float a = templ[size_t(j) * patch + i];
      const float b = window[size_t(dy + j) * span + dx + i];
      if (std::isnan(a) || std::isnan(b)) continue;
      sa += a, sb += b, saa += double(a) * a, sbb += double(b) * b, sab += double(a) * b;
      ++n;
    }
  const double lowest = -std::numeric_limits<double>::infinity();
  if (n < min_n) return lowest;
  const double va = saa - sa * sa / double(n), vb = sbb - sb * sb / double(n);
  if (!(va > 1e-12) || !(vb > 1e-12)) return lowest;
  return (sab - sa * sb / double(n)) / std::sqrt(va * vb);
}

// Claim (calibration.h CorrelationGrid): the patch search's correlations, several shifts at a
// time, are those of one shift at a time, bit for bit, under every instruction set: with a
// window without holes and with holes (a LiDAR image's), a template with and without holes, a
// flat window (-inf), and search rows that are not a multiple of the lanes.
TEST(CorrelationGridTest, IsEachShiftsCorrelationBitForBit) {
  int isas = 0;
  for (memory::Isa isa : {memory::Isa::kBaseline, memory::Isa::kAvx2, memory::Isa::kX86_64_V4}) {
    if (!memory::Supports(isa)) continue;
    memory::SetIsaCap(isa);
    ++isas;
    std::mt19937 rng(3);
    std::uniform_real_distribution<float> u(0.0f, 1.0f);
    const float nan = std::numeric_limits<float>::quiet_NaN();
    size_t shifts = 0, unequal = 0, lowest = 0;
    for (const auto& [R, S] : {std::pair{7, 8}, std::pair{2, 3}, std::pair{4, 11}}) {
      for (const double holes : {0.0, 0.1, 0.6}) {
        for (const bool template_holes : {false, true}) {
          for (const bool flat : {false, true}) {
            const int patch = 2 * R + 1, span = 2 * (R + S) + 1, side = 2 * S + 1;
            std::vector<float> templ(size_t(patch) * patch), window(size_t(span) * span);
            for (float& t : templ) t = template_holes && u(rng) < 0.2f ? nan : u(rng);
            for (float& w : window) w = holes > 0 && u(rng) < holes ? nan : flat ? 0.5f : u(rng);
            const size_t min_n = templ.size() / 2;
            const std::vector<double> grid = internal::CorrelationGrid(templ, window, R, S, min_n);
            ASSERT_EQ(grid.size(), size_t(side) * side);
            for (int dy = 0; dy < side; ++dy)
              for (int dx = 0; dx < side; ++dx) {
                const double want = OneShift(templ, window, R, S, dx, dy, min_n);
                const double got = grid[size_t(dy) * side + dx];
                ++shifts;
                lowest += std::isinf(want);
                if (!(got == want)) {
                  ++unequal;
                  ADD_FAILURE() << "R " << R << " S " << S << " holes " << holes << " shift (" << dx
                                << ", " << dy << "): " << got << " against " << want;
                }
              }
          }
        }
      }
    }
    memory::SetIsaCap(memory::Isa::kX86_64_V4);
    std::printf("cap %d: %zu shifts, %zu of them -inf (too few pairs, or flat), %zu unequal\n",
                int(isa), shifts, lowest, unequal);
    EXPECT_EQ(unequal, 0u);
    EXPECT_GT(lowest, 0u);
    EXPECT_LT(lowest, shifts);
  }
  EXPECT_GE(isas, 1);
}

}  // namespace
}  // namespace vasl::ingest

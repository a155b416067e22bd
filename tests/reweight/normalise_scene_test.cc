// VASL-MODEL §7, multi-scan radiometric normalisation on a scene: gains planted in the room's
// synthetic panoramas are recovered by `Engine::Normalise`, and the fused colour under the
// normalised profile is closer to the truth than before.
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <filesystem>

#include <gtest/gtest.h>

#include "lattice/engine.h"
#include "lattice/fusion/fuse.h"
#include "tests/scenes/synthetic_scene.h"

namespace vasl {
namespace {
namespace fs = std::filesystem;

/// Fused colour against the albedo on the room's walls, per channel after the best global
/// scale (normalisation fixes how scans disagree, not the site's absolute brightness):
/// sqrt(mean((f − s·a)² / a²)), the worst channel.
double WallError(const scenes::SyntheticRoom& room, const records::VosselGeometry& g,
                 const records::FusedModality& rgb, size_t* used) {
  const scenes::Aabb& box = room.RoomBounds();
  std::vector<std::pair<Eigen::Vector3f, Eigen::Vector3f>> pairs;  // (fused, albedo)
  for (size_t k = 0; k < g.size(); ++k) {
    const Eigen::Vector3d x = g.centroid_m[k].cast<double>();
    int face = -1;
    if (std::abs(x.y() - box.max_m.y()) < 0.01) face = scenes::kFaceWallYMax;
    if (std::abs(x.x() - box.max_m.x()) < 0.01) face = scenes::kFaceWallXMax;
    if (std::abs(x.x() - box.min_m.x()) < 0.01) face = scenes::kFaceWallXMin;
    if (face < 0 || rgb.weight[k] <= 0.0f || x.z() < 0.1 || x.z() > box.max_m.z() - 0.1) continue;
    pairs.push_back({Eigen::Vector3f(rgb.value[3 * k], rgb.value[3 * k + 1], rgb.value[3 * k + 2]),
                     room.Albedo(x, face)});
  }
  *used = pairs.size();
  double worst = 0.0;
  for (int c = 0; c < 3; ++c) {
    double fa = 0.0, aa = 0.0;
    for (const auto& [f, a] : pairs) {
      fa += double(f[c]) / a[c];
      aa += 1.0;
    }
    const double s = fa / aa;  // least squares of f/a − s
    double e2 = 0.0;
    for (const auto& [f, a] : pairs) e2 += std::pow(double(f[c]) / a[c] - s, 2);
    worst = std::max(worst, std::sqrt(e2 / aa));
  }
  return worst;
}

TEST(NormaliseSceneTest, RecoversPlantedGainsAndBringsFusionCloserToTheTruth) {
  const fs::path root = fs::temp_directory_path() / ("vasl-normalise-" + std::to_string(::getpid()));
  fs::remove_all(root);
  auto engine = Engine::Open(root);
  ASSERT_TRUE(engine.ok()) << engine.status();
  store::ProjectSettings settings;
  settings.vossel_size_m = 0.05;
  ASSERT_TRUE((*engine)->CreateProject("n", settings).ok());
  const scenes::SyntheticRoom room = scenes::SyntheticRoom::Default();
  // Per-station camera gains (≤ 1 so that nothing clips in the 8-bit panoramas).
  const std::vector<std::array<double, 3>> planted = {
      {0.80, 0.95, 0.90}, {1.00, 0.85, 0.95}, {0.90, 1.00, 0.80}, {0.95, 0.90, 1.00}};
  ASSERT_EQ(room.Stations().size(), planted.size());
  for (size_t i = 0; i < planted.size(); ++i) {
    auto scan = scenes::MakeScanInput(room, i, scenes::LidarSettings::Small(i + 1), 512, 2);
    ASSERT_TRUE(scan.ok()) << scan.status();
    ASSERT_EQ(scan->panoramas.size(), 1u);
    scenes::Panorama pano = scenes::RenderPanorama(room, scan->panoramas[0].pose, 512, 256, 2);
    for (size_t p = 0; p < pano.rgb.size(); ++p) pano.rgb[p] *= float(planted[i][p % 3]);
    auto png = scenes::EncodePng(pano);
    ASSERT_TRUE(png.ok()) << png.status();
    scan->panoramas[0].encoded_image = std::move(*png);
    ASSERT_TRUE((*engine)->IngestScan("n", *scan).ok());
  }
  auto outcome = (*engine)->Normalise("n", "", "");
  ASSERT_TRUE(outcome.ok()) << outcome.status();
  EXPECT_EQ(outcome->profile.profile.name, "normalised");
  auto scans = (*engine)->ListScans("n");
  ASSERT_TRUE(scans.ok());

  // Expected: a_m ∝ 1/g_m with mean 1 per channel.
  std::array<double, 3> mean_inv{};
  for (const auto& g : planted) {
    for (int c = 0; c < 3; ++c) mean_inv[c] += 1.0 / g[c] / double(planted.size());
  }
  double worst_gain = 0.0;
  for (size_t i = 0; i < scans->size(); ++i) {
    for (const store::SourceInfo& src : (*scans)[i].sources) {
      if (src.modality != records::Modality::kRgb) continue;
      auto it = outcome->profile.profile.channel_gain.find(src.id);
      ASSERT_NE(it, outcome->profile.profile.channel_gain.end()) << "no gain for source " << src.id;
      for (int c = 0; c < 3; ++c) {
        const double expected = 1.0 / planted[i][c] / mean_inv[c];
        worst_gain = std::max(worst_gain, std::abs(it->second[c] / expected - 1.0));
      }
    }
  }
  // The fused colour under the default profile and under the normalised one.
  auto st = store::ProjectStore::Open(root / "n");
  ASSERT_TRUE(st.ok());
  auto snap = (*st)->LoadSnapshot((*st)->head_version());
  ASSERT_TRUE(snap.ok());
  const records::VosselGeometry& g = (*snap)->geometry;
  auto after = fusion::Fuse((*snap)->records, g.size(), g.vossel_size_m, outcome->profile.profile);
  ASSERT_TRUE(after.ok());
  size_t n_before = 0, n_after = 0;
  const double before_err =
      WallError(room, g, (*snap)->fused.by_modality.at(records::Modality::kRgb), &n_before);
  const double after_err =
      WallError(room, g, after->by_modality.at(records::Modality::kRgb), &n_after);
  std::printf("normalisation: worst relative gain error %.4f (%lld vossels, %lld pair terms); "
              "fused colour vs albedo on %zu wall vossels, relative RMS after a global scale: "
              "%.4f before, %.4f after; cost R %.3g -> %.3g\n",
              worst_gain, (long long)outcome->solve.vossels_used, (long long)outcome->solve.pairs_used,
              n_after, before_err, after_err, outcome->solve.cost_before[0],
              outcome->solve.cost_after[0]);
  EXPECT_LT(worst_gain, 0.02);
  EXPECT_LT(after_err, before_err);
  EXPECT_GT(n_after, 5000u);
  fs::remove_all(root);
}

}  // namespace
}  // namespace vasl

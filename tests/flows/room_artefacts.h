// What the §9 flow tests share: the synthetic room's stations ingested into a fresh project,
// and the fused colour error of chosen vossels against the albedo a pose sees.
#pragma once

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <memory>
#include <utility>
#include <vector>

#include <gtest/gtest.h>

#include "lattice/engine.h"
#include "lattice/fusion/fuse.h"
#include "lattice/store/project_store.h"
#include "tests/scenes/synthetic_scene.h"

namespace vasl {
namespace {

constexpr double kVosselM = 0.05;

/// A project "room" in `dir` with the synthetic room's stations ingested (LiDAR and clean
/// panoramas).
std::unique_ptr<Engine> RoomWithStations(const std::filesystem::path& dir,
                                         const scenes::SyntheticRoom& room) {
  std::filesystem::remove_all(dir);
  auto engine = Engine::Open(dir);
  EXPECT_TRUE(engine.ok()) << engine.status();
  if (!engine.ok()) return nullptr;
  store::ProjectSettings settings;
  settings.vossel_size_m = kVosselM;
  EXPECT_TRUE((*engine)->CreateProject("room", settings).ok());
  for (size_t i = 0; i < room.Stations().size(); ++i) {
    auto scan = scenes::MakeScanInput(room, i, scenes::LidarSettings::Small(i + 1), 512);
    EXPECT_TRUE(scan.ok()) << scan.status();
    if (scan.ok()) EXPECT_TRUE((*engine)->IngestScan("room", *scan).ok());
  }
  return std::move(*engine);
}

/// HEAD after `scan` was ingested into "room" of the engine over `dir`, and the id of the
/// scan's first source (its camera).
struct AfterIngest {
  std::shared_ptr<const store::Snapshot> snap;
  int32_t camera = -1;
};
AfterIngest IngestAndLoad(Engine& engine, const std::filesystem::path& dir,
                          const ingest::ScanInput& scan) {
  AfterIngest out;
  const absl::Status ingested = engine.IngestScan("room", scan).status();
  EXPECT_TRUE(ingested.ok()) << ingested;
  auto st = store::ProjectStore::Open(dir / "room");
  EXPECT_TRUE(st.ok()) << st.status();
  if (!ingested.ok() || !st.ok()) return out;
  auto snap = (*st)->LoadSnapshot((*st)->head_version());
  EXPECT_TRUE(snap.ok()) << snap.status();
  auto scans = (*st)->ListScans();
  EXPECT_TRUE(scans.ok()) << scans.status();
  if (!snap.ok() || !scans.ok()) return out;
  out.snap = std::move(*snap);
  out.camera = scans->back().sources.at(0).id;
  return out;
}

/// The default profile with κ of confidence factor `factor` set to `kappa`.
fusion::WeightingProfile ProfileWith(int factor, double kappa) {
  fusion::WeightingProfile profile;
  profile.kappa[size_t(factor)] = kappa;
  return profile;
}

/// The mean |error| against the albedo seen from `pose` of the fused colour of the vossels
/// marked in `affected` (those whose surface the pose sees within a vossel), under `profile`;
/// and how many.
std::pair<double, size_t> FusedError(const records::RecordSet& rec,
                                     const records::VosselGeometry& g,
                                     const std::vector<uint8_t>& affected,
                                     const scenes::SyntheticRoom& room, const geometry::Pose& pose,
                                     const fusion::WeightingProfile& profile) {
  auto fused = fusion::Fuse(rec, g.size(), g.vossel_size_m, profile);
  EXPECT_TRUE(fused.ok()) << fused.status();
  if (!fused.ok()) return {0.0, 0};
  const records::FusedModality& rgb = fused->by_modality.at(records::Modality::kRgb);
  double err = 0.0;
  size_t n = 0;
  for (size_t k = 0; k < g.size(); ++k) {
    if (!affected[k] || !(rgb.weight[k] > 0.0f)) continue;
    const Eigen::Vector3d x = g.FrameCentroid(k).cast<double>();
    const scenes::SceneHit hit = room.Intersect(pose.o_world, (x - pose.o_world).normalized(), 1e9);
    if (!hit.valid || std::abs(hit.t_m - (x - pose.o_world).norm()) > kVosselM) continue;
    const Eigen::Vector3f& albedo = hit.albedo_linear;
    for (int c = 0; c < 3; ++c) err += std::abs(rgb.value[3 * k + c] - albedo[c]) / 3.0;
    ++n;
  }
  return {err / double(std::max<size_t>(1, n)), n};
}

}  // namespace
}  // namespace vasl

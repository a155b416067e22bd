// Claims of flare at ingest (VASL-MODEL §9, §6, §7): in a room of plain tiled faces, a panorama
// facing a wall with bright sources planted on it, each with a broad veil of glare, is ingested
// beside the stations' clean panoramas. Most of its records where the glare outweighs the
// surface's own light 1.5 times are invalidated (no colour is taken from them) and none where
// it is under half of it; most of those where it adds over a fifth have conf[flare] < 1; those
// far from the sources keep 1. Fusion that weighs the map (invalidation, then κ = 2) gives the
// affected vossels a colour closer to their albedo than fusion that ignores it, undoing at
// least half of the error the glare added over the clean stations' colour, from the records
// alone.
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <vector>

#include <gtest/gtest.h>

#include "tests/flows/room_artefacts.h"

namespace vasl {
namespace {
namespace fs = std::filesystem;

constexpr int kPanoW = 2048;

/// A bright source planted in the panorama: a disk at 16× the clip level with a veil of glare
/// g·(1 + (d/α)²)^−β at a distance d (pixels) from its centre.
struct Source {
  double u, v, radius_px, glare, alpha_px, beta;
  double Glare(double x, double y) const {
    const double dx = std::min(std::abs(x - u), kPanoW - std::abs(x - u));  // columns wrap
    const double d = std::hypot(dx, y - v) / alpha_px;
    return glare * std::pow(1.0 + d * d, -beta);
  }
  bool Inside(double x, double y) const {
    const double dx = std::min(std::abs(x - u), kPanoW - std::abs(x - u));
    return std::hypot(dx, y - v) <= radius_px;
  }
};

TEST(FlareFlowTest, GlareInvalidatesAndLowersTheRecordsAndWeighingItMendsTheColour) {
  const fs::path dir =
      fs::temp_directory_path() / ("vasl-flare-flow-test-" + std::to_string(::getpid()));
  // Plain tiled faces: a sharp texture, whose darkest pixels the veil lifts (§9), without the
  // smooth albedo gradients a veil cannot be told from in one image.
  const scenes::SyntheticRoom room = scenes::SyntheticRoom::Default().WithTiles(0.1, true);
  std::unique_ptr<Engine> engine = RoomWithStations(dir, room);
  ASSERT_TRUE(engine != nullptr);
  // A panorama 1.2 m from wall y = 0, facing it (so that the wall fills the field around the
  // sources), with two sources on the wall, their veils 0.4 and 0.5 of the clip level at the
  // centre, 40 and 50 px wide.
  geometry::Pose pose;
  pose.o_world = Eigen::Vector3d(3.0, 1.2, 1.5);
  pose.q_world_sensor = Eigen::Quaterniond(Eigen::AngleAxisd(-M_PI / 2, Eigen::Vector3d::UnitZ()));
  scenes::Panorama pano = scenes::RenderPanorama(room, pose, kPanoW, kPanoW / 2, 2);
  const std::vector<Source> sources = {{900, 480, 5, 0.4, 40, 1.1},
                                       {1150, 560, 6, 0.5, 50, 1.2}};
  for (int y = 0; y < kPanoW / 2; ++y) {
    for (int x = 0; x < kPanoW; ++x) {
      const size_t p = size_t(y) * kPanoW + x;
      double glare = 0.0;
      bool source = false;
      for (const Source& s : sources) {
        glare += s.Glare(x + 0.5, y + 0.5);
        source |= s.Inside(x + 0.5, y + 0.5);
      }
      for (int c = 0; c < 3; ++c) {
        pano.rgb[3 * p + c] = source ? 1.0f : std::min(1.0f, pano.rgb[3 * p + c] + float(glare));
      }
    }
  }
  auto flared = scenes::PanoramaScan("flared", pose, pano);
  ASSERT_TRUE(flared.ok()) << flared.status();
  const AfterIngest after = IngestAndLoad(*engine, dir, *flared);
  ASSERT_TRUE(after.snap != nullptr);
  const int32_t camera = after.camera;
  const records::RecordSet& rec = after.snap->records;
  const records::VosselGeometry& g = after.snap->geometry;

  // The camera's records, by the glare under their pixel against the surface's own light.
  size_t dominated = 0, dominated_invalid = 0, lowered = 0, lowered_below = 0, far = 0;
  size_t far_one = 0, wrongly_invalid = 0;
  std::vector<uint8_t> affected(g.size(), 0);
  for (size_t i = 0; i < rec.size(); ++i) {
    if (rec.scan[i] != camera) continue;
    const double u = rec.uv_px[2 * i], v = rec.uv_px[2 * i + 1];
    const float conf = rec.conf[i * records::kConfidenceCount + records::kConfFlare];
    const bool invalid = (rec.flags[i] & records::kFlagInvalidated) != 0;
    double glare = 0.0, nearest = 1e9;
    bool source = false;
    for (const Source& s : sources) {
      glare += s.Glare(u, v);
      source |= s.Inside(u, v);
      const double dx = std::min(std::abs(u - s.u), kPanoW - std::abs(u - s.u));
      nearest = std::min(nearest, std::hypot(dx, v - s.v));
    }
    if (source) continue;
    const Eigen::Vector3d x = g.FrameCentroid(size_t(rec.vossel[i])).cast<double>();
    const scenes::SceneHit hit =
        room.Intersect(pose.o_world, (x - pose.o_world).normalized(), 1e9);
    const double own = hit.valid ? std::max(0.02f, hit.albedo_linear.maxCoeff()) : 0.5;
    if (glare > 1.5 * own && own + glare < 0.95) {
      ++dominated;
      dominated_invalid += invalid;
    } else if (glare > 0.2 * own && glare > 0.02 && own + glare < 0.95 && !invalid) {
      ++lowered;
      lowered_below += conf < 1.0f;
    } else if (nearest > 400.0) {
      ++far;
      far_one += conf == 1.0f && !invalid;
    }
    wrongly_invalid += invalid && glare < 0.5 * own;
    if (conf < 1.0f || invalid) affected[size_t(rec.vossel[i])] = 1;
  }
  std::printf("flared camera's records: %zu where the glare is over 1.5x the own light (%zu "
              "invalidated), %zu where it adds over a fifth (%zu below 1), %zu far from any "
              "source (%zu at 1); %zu invalidated with glare under half the own light\n",
              dominated, dominated_invalid, lowered, lowered_below, far, far_one,
              wrongly_invalid);
  EXPECT_GT(dominated, 10u);
  EXPECT_GE(dominated_invalid, size_t(0.7 * double(dominated)));
  EXPECT_GT(lowered, 200u);
  EXPECT_GE(lowered_below, size_t(0.8 * double(lowered)));
  EXPECT_GT(far, 10000u);
  EXPECT_GE(far_one, size_t(0.999 * double(far)));
  EXPECT_EQ(wrongly_invalid, 0u);

  // Fused colour of the affected vossels against their albedo: the same records fused ignoring
  // the map (its invalid flags cleared, κ_flare = 0) and weighing it (flags kept, κ = 2).
  records::RecordSet ignored = rec;
  for (int8_t& f : ignored.flags) f = int8_t(f & ~records::kFlagInvalidated);
  auto fused_error = [&](const records::RecordSet& records, double kappa) {
    return FusedError(records, g, affected, room, pose, ProfileWith(records::kConfFlare, kappa));
  };
  // The clean stations alone: what the glare's damage is measured from.
  records::RecordSet clean = rec;
  for (size_t i = 0; i < rec.size(); ++i) {
    if (rec.scan[i] == camera) clean.flags[i] = int8_t(clean.flags[i] | records::kFlagInvalidated);
  }
  const auto [ignoring, n0] = fused_error(ignored, 0.0);
  const auto [invalidating, n1] = fused_error(rec, 0.0);
  const auto [weighing, n2] = fused_error(rec, 2.0);
  const auto [baseline, n3] = fused_error(clean, 0.0);
  const double undone = (ignoring - weighing) / (ignoring - baseline);
  std::printf("fused colour of %zu vossels the glare reaches, mean |error| against the albedo: "
              "%.4f ignoring the map, %.4f leaving the invalid records out (kappa 0), %.4f "
              "weighing the rest too (kappa 2), %.4f without the flared camera: the map undoes "
              "%.0f%% of the glare's damage\n", n0, ignoring, invalidating, weighing, baseline,
              100.0 * undone);
  EXPECT_GT(n0, 200u);
  EXPECT_LT(invalidating, ignoring);
  EXPECT_LT(weighing, invalidating);
  EXPECT_GE(undone, 0.5);
  engine.reset();
  fs::remove_all(dir);
}

}  // namespace
}  // namespace vasl

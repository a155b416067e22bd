// Claims of the random site (random_site.h) and of the range grid helper on scans with rays
// that return nothing.
#include "tests/scenes/random_site.h"

#include <algorithm>
#include <cmath>
#include <cstdio>

#include <gtest/gtest.h>

#include "lattice/geometry/equirect.h"

namespace vasl::scenes {
namespace {

using Eigen::Vector3d;

LidarSettings Coarse(uint64_t seed) {
  LidarSettings s;
  s.azimuth_steps = 360;
  s.elevation_steps = 180;
  s.seed = seed;
  return s;
}

// Claim: the same seed gives the same site, and its stations keep their clearance (camera
// included); every LiDAR return of a station lies on the surface Intersect reports within 4σ
// of range noise, on a unit normal facing the station, and a closed room returns every ray.
TEST(RandomSiteSceneTest, StationsAreClearAndReturnsLieOnTheSurfaces) {
  for (uint64_t seed : {1, 2, 3}) {
    const RandomSite site(seed, 6, 5), again(seed, 6, 5);
    ASSERT_EQ(site.Stations().size(), 5u);
    for (size_t s = 0; s < site.Stations().size(); ++s) {
      EXPECT_EQ(site.Stations()[s].o_world, again.Stations()[s].o_world);
      for (const Vector3d& o :
           {site.Stations()[s].o_world, CameraPoseForStation(site.Stations()[s]).o_world}) {
        for (const OrientedBox& box : site.Boxes()) {
          EXPECT_GE(box.DistanceTo(o), RandomSite::kClearanceM);
        }
      }
    }
    const LidarSettings settings = Coarse(seed);
    const geometry::Pose pose = site.Stations()[0];
    const LidarScan scan = GenerateLidar(site, pose, settings);
    const size_t n = scan.intensity.size();
    int kept_rows = 0;
    for (int j = 0; j < settings.elevation_steps; ++j) kept_rows += LidarRowKept(settings, j);
    EXPECT_EQ(n, size_t(kept_rows) * settings.azimuth_steps);
    size_t off = 0, bad_normal = 0;
    for (size_t k = 0; k < n; ++k) {
      const Vector3d p(scan.xyz_sensor_m[3 * k], scan.xyz_sensor_m[3 * k + 1],
                       scan.xyz_sensor_m[3 * k + 2]);
      const Vector3d d = pose.DirectionToWorld(p.normalized());
      const SceneHit hit = site.Intersect(pose.o_world, d, 1e9);
      ASSERT_TRUE(hit.valid);
      off += std::abs(p.norm() - hit.t_m) > 4.0 * settings.range_noise_m + 1e-6;
      bad_normal += std::abs(hit.n_world.norm() - 1.0) > 1e-9 || hit.n_world.dot(d) > 0.0;
    }
    std::printf("seed %llu: %zu returns, %zu beyond 4 sigma, %zu bad normals\n",
                (unsigned long long)seed, n, off, bad_normal);
    EXPECT_LE(off, n / 1000);
    EXPECT_EQ(bad_normal, 0u);
  }
}

// Claim (synthetic_scene.h SetRangeGrid): each point gets the grid cell its ray was cast from:
// in a closed room the cells of every kept row in order; in a yard under the open sky, where
// rays upward return nothing, fewer points than cells, each in the cell whose centre direction
// it lies along (within 10⁻⁴ of a cell), in the grid's row-major order.
TEST(RandomSiteSceneTest, RangeGridCellsAreTheRaysOfTheReturns) {
  const LidarSettings settings = Coarse(5);
  const geometry::EquirectSize grid{settings.azimuth_steps, settings.elevation_steps};
  {
    const RandomSite room(2, 6, 1);
    const LidarScan scan = GenerateLidar(room, room.Stations()[0], settings);
    ingest::LidarData lidar;
    lidar.xyz_sensor_m = scan.xyz_sensor_m;
    SetRangeGrid(settings, &lidar);
    std::vector<uint32_t> every;
    for (int j = 0; j < settings.elevation_steps; ++j) {
      if (!LidarRowKept(settings, j)) continue;
      for (int i = 0; i < settings.azimuth_steps; ++i) {
        every.push_back(uint32_t(j * settings.azimuth_steps + i));
      }
    }
    EXPECT_EQ(lidar.grid_cell, every);
  }
  const RandomSite yard(11, 8, 1, /*outdoor=*/true);
  ASSERT_EQ(yard.Stations().size(), 1u);
  const LidarScan scan = GenerateLidar(yard, yard.Stations()[0], settings);
  ingest::LidarData lidar;
  lidar.xyz_sensor_m = scan.xyz_sensor_m;
  SetRangeGrid(settings, &lidar);
  const size_t n = lidar.xyz_sensor_m.size() / 3;
  ASSERT_EQ(lidar.grid_cell.size(), n);
  EXPECT_LT(n, size_t(settings.azimuth_steps) * settings.elevation_steps * 3 / 4);
  size_t off_centre = 0;
  for (size_t k = 0; k < n; ++k) {
    if (k > 0) ASSERT_LT(lidar.grid_cell[k - 1], lidar.grid_cell[k]);
    const Vector3d p(lidar.xyz_sensor_m[3 * k], lidar.xyz_sensor_m[3 * k + 1],
                     lidar.xyz_sensor_m[3 * k + 2]);
    const Eigen::Vector2d uv = geometry::EquirectProject(p.normalized(), grid);
    const int i = int(lidar.grid_cell[k] % uint32_t(settings.azimuth_steps));
    const int j = int(lidar.grid_cell[k] / uint32_t(settings.azimuth_steps));
    off_centre += std::abs(uv.x() - (i + 0.5)) > 1e-4 || std::abs(uv.y() - (j + 0.5)) > 1e-4;
  }
  std::printf("yard: %zu returns of %d cells\n", n,
              settings.azimuth_steps * settings.elevation_steps);
  EXPECT_EQ(off_centre, 0u);
}

}  // namespace
}  // namespace vasl::scenes

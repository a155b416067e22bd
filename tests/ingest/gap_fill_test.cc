// Surface connectivity from a scan's range grid (voxelise.h, BinLidar; issue "Renders …": no
// see-through gaps): a LiDAR coarser than the lattice leaves most surface vossels of a room
// without a return, so rays pass between them. With the scan's range grid the gaps between
// neighbouring returns on one surface are filled: the vossels a dense scan from the same
// station finds are covered, and no fill vossel lies off the room's surfaces (none bridges a
// depth edge such as the box in front of the wall).
#include <cstdio>
#include <set>

#include <gtest/gtest.h>

#include "lattice/ingest/voxelise.h"
#include "tests/scenes/synthetic_scene.h"

namespace vasl::ingest {
namespace {

constexpr double kVosselM = 0.02;

// The station's LiDAR scan with its range grid: GenerateLidar casts the kept rows of an
// azimuth × elevation ray grid, row-major.
LidarSource Scan(const scenes::SyntheticRoom& room, int azimuth_steps, bool with_grid) {
  scenes::LidarSettings settings;
  settings.azimuth_steps = azimuth_steps;
  settings.elevation_steps = azimuth_steps / 2;
  scenes::LidarScan scan = scenes::GenerateLidar(room, room.Stations()[0], settings);
  LidarSource src;
  src.id = 1;
  src.pose = room.Stations()[0];
  src.xyz_sensor_m = std::move(scan.xyz_sensor_m);
  src.intensity = std::move(scan.intensity);
  if (with_grid) {
    LidarData grid;
    grid.xyz_sensor_m = src.xyz_sensor_m;  // each point's cell is the one its direction is in
    scenes::SetRangeGrid(settings, &grid);
    src.grid_rows = grid.grid_rows;
    src.grid_columns = grid.grid_columns;
    src.grid_cell = std::move(grid.grid_cell);
    EXPECT_EQ(src.grid_cell.size(), src.point_count());
  }
  return src;
}

std::set<openvdb::Coord> Vossels(const LidarSource& src) {
  absl::StatusOr<BinnedLidar> binned = BinLidar(src, kVosselM);
  EXPECT_TRUE(binned.ok()) << binned.status();
  return std::set<openvdb::Coord>(binned->coord.begin(), binned->coord.end());
}

TEST(GapFillTest, ARangeGridClosesTheGapsOfACoarseScanAndStaysOnTheSurfaces) {
  const scenes::SyntheticRoom room = scenes::SyntheticRoom::Default();
  const std::set<openvdb::Coord> dense = Vossels(Scan(room, 7200, false));  // 0.05°: ≤ 8 mm
  const LidarSource coarse = Scan(room, 720, false);                        // 0.5°: 2-5 cm
  const std::set<openvdb::Coord> bare = Vossels(coarse);
  const std::set<openvdb::Coord> filled = Vossels(Scan(room, 720, true));

  const auto covered = [&](const std::set<openvdb::Coord>& got) {
    size_t n = 0;
    for (const openvdb::Coord& c : dense) n += got.count(c);
    return double(n) / double(dense.size());
  };
  // Fill vossels lie on a surface: the ray from the scanner towards one meets the room within
  // one vossel diagonal of it.
  const Eigen::Vector3d o = room.Stations()[0].o_world;
  size_t off = 0, extra = 0;
  for (const openvdb::Coord& c : filled) {
    if (bare.count(c)) continue;
    ++extra;
    const Eigen::Vector3d x = kVosselM * Eigen::Vector3d(c.x(), c.y(), c.z());
    const double r = (x - o).norm();
    const scenes::SceneHit hit = room.Intersect(o, (x - o) / r, 100.0);
    if (!hit.valid || std::abs(hit.t_m - r) > std::sqrt(3.0) * kVosselM) ++off;
  }
  std::printf("dense scan: %zu vossels; coarse scan: %zu vossels (%.2f%% of the dense ones), "
              "with its range grid: %zu (%.2f%%), %zu fill vossels, %zu off the surfaces\n",
              dense.size(), bare.size(), 100 * covered(bare), filled.size(),
              100 * covered(filled), extra, off);
  EXPECT_LT(covered(bare), 0.6);      // the gaps rays pass through
  EXPECT_GE(covered(filled), 0.97);   // closed
  EXPECT_TRUE(std::includes(filled.begin(), filled.end(), bare.begin(), bare.end()));
  EXPECT_LE(double(off), 0.001 * double(extra));
}

// Claim: fill points join the sums in grid order, so the binning does not depend on the
// thread count or on the order the points were sent in within a grid cell's neighbourhood:
// two binnings of the same scan give the same bits.
TEST(GapFillTest, BinningWithAGridIsDeterministic) {
  const scenes::SyntheticRoom room = scenes::SyntheticRoom::Default();
  const LidarSource src = Scan(room, 720, true);
  absl::StatusOr<BinnedLidar> a = BinLidar(src, kVosselM), b = BinLidar(src, kVosselM);
  ASSERT_TRUE(a.ok() && b.ok());
  ASSERT_EQ(a->size(), b->size());
  for (size_t v = 0; v < a->size(); ++v) {
    ASSERT_EQ(a->coord[v], b->coord[v]);
    ASSERT_EQ(a->count[v], b->count[v]);
    ASSERT_EQ(a->sums[v].sum_m, b->sums[v].sum_m);
  }
}

}  // namespace
}  // namespace vasl::ingest

// VASL-MODEL §5, rule 3 of flows/change.h on the corridor site: of a revisited source's
// vossels, those a revisit recomputes (RevisitScope::only) are exactly the changed ones and the
// unchanged ones with a visibility test sample where the changed splats' depth panorama lies
// nearer than the sample's threshold: the vossels ScopeOf passes over without testing (by
// reach cell, by pixel, with the tolerance) are those such a test finds lit everywhere.
#include <algorithm>
#include <cstdint>
#include <set>
#include <vector>

#include <gtest/gtest.h>

#include "lattice/flows/change.h"
#include "lattice/flows/flows.h"
#include "lattice/ingest/sample.h"
#include "lattice/ingest/visibility.h"
#include "lattice/tiles/tile_split.h"
#include "tests/scenes/corridor_lattice.h"

namespace vasl::flows::internal {
namespace {

using RevisitScopeTest = scenes::CorridorLatticeTest;
constexpr double kVosselM = scenes::CorridorLatticeTest::kVosselM;

// Claim: ScopeOf's `only` = the changed vossels ∪ the unchanged ones that the changed splats'
// panorama (dilated as the source's) leaves not wholly lit, for a LiDAR and a camera seeing the
// change from near and from down the corridor; and the change shadows some unchanged vossels
// of each (so the claim is not met by an empty set).
TEST_F(RevisitScopeTest, RecomputedVosselsAreTheChangedAndThoseTheChangeShadows) {
  const records::VosselGeometry& g = *geometry_;
  const std::vector<geometry::Pose>& stations = site_->Stations();
  ASSERT_GE(stations.size(), 8u);
  // The change: every vossel within 1.5 m of a point between stations 5 and 6, as it is now
  // (appeared or reframed; no old state).
  const Eigen::Vector3d centre =
      0.5 * (stations[5].o_world + stations[6].o_world) + Eigen::Vector3d(0.3, 0.4, -0.2);
  std::vector<uint8_t> changed(g.size(), 0);
  ChangedSplats splats;
  splats.splats.vossel_size_m = g.vossel_size_m;
  for (size_t k = 0; k < g.size(); ++k) {
    if ((g.FrameCentroid(k).cast<double>() - centre).norm() > 1.5) continue;
    changed[k] = 1;
    splats.splats.coord.push_back(g.coord[k]);
    splats.splats.centroid_m.push_back(g.FrameCentroid(k));
    splats.splats.normal.push_back(g.FrameNormal(k));
  }
  ASSERT_GT(splats.splats.size(), 500u);
  const std::vector<uint8_t> candidates(g.size(), 1);
  const int B = BlockVossels(64);
  const std::vector<tiles::TileKey> block_of = tiles::TilesOfVossels(g, B);
  const std::set<tiles::TileKey> all(block_of.begin(), block_of.end());
  const std::vector<tiles::TileKey> blocks(all.begin(), all.end());
  std::vector<int32_t> block_number(g.size());
  for (size_t k = 0; k < g.size(); ++k) {
    block_number[k] = int32_t(std::lower_bound(blocks.begin(), blocks.end(), block_of[k]) -
                              blocks.begin());
  }

  for (const int station : {4, 7, 1}) {
    for (const bool lidar : {true, false}) {
      SourceRef src;
      src.info.id = 1;
      src.info.pose = stations[size_t(station)];
      if (lidar) {
        src.info.modality = records::Modality::kLidar;
        src.info.point_count = 720 * 360;
        src.info.divergence_rad = 0.3e-3;
      } else {
        src.info.modality = records::Modality::kRgb;
        src.info.width_px = 1024;
        src.info.height_px = 512;
      }
      const RevisitScope scope =
          ScopeOf(src, g, candidates, changed, splats, blocks, block_number, B, nullptr);

      // Every unchanged vossel tested against the changed splats alone.
      const ingest::DepthView view =
          lidar ? ingest::LidarDepthView(size_t(src.info.point_count), src.info.divergence_rad)
                : ingest::CameraDepthView(CameraOf(src.info, 0), src.info.width_px,
                                          src.info.height_px);
      ingest::DepthPanorama s = ingest::RenderDepthPanorama(splats.splats, src.info.pose,
                                                            view.size, view.divergence_rad);
      ingest::DilateDepthPanorama(s, view.dilate_px);
      std::vector<uint8_t> unchanged(g.size());
      for (size_t k = 0; k < g.size(); ++k) unchanged[k] = !changed[k];
      const std::vector<float> lit =
          ingest::ComputeVisibility(g, s, ingest::DepthToleranceM(kVosselM), &unchanged,
                                    view.slope_pixels, /*shadow_by_cells=*/false);
      size_t shadowed = 0, differ = 0;
      for (size_t k = 0; k < g.size(); ++k) {
        const bool expect = changed[k] || lit[k] < 1.0f;
        shadowed += !changed[k] && lit[k] < 1.0f;
        differ += expect != (scope.only[k] != 0);
      }
      EXPECT_EQ(differ, 0u) << (lidar ? "LiDAR" : "camera") << " at station " << station;
      EXPECT_GT(shadowed, 0u) << (lidar ? "LiDAR" : "camera") << " at station " << station;
    }
  }
}

}  // namespace
}  // namespace vasl::flows::internal

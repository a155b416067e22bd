// VASL-MODEL §5 on the synthetic room: vossels on the wall behind the occluder are in shadow
// from the station the box hides them from and lit from another; vossels at the shadow's edge
// get a fraction strictly between 0 and 1; classification agrees with the analytic answer.
#include "lattice/ingest/visibility.h"

#include <cmath>

#include <gtest/gtest.h>

#include "lattice/ingest/voxelise.h"
#include "tests/scenes/synthetic_scene.h"

namespace vasl::ingest {
namespace {

using scenes::Aabb;

constexpr double kVosselM = 0.05;
// The lattice quantises the occluder to whole vossels, so its shadow's edge can move by up to
// h/2 seen from the occluder, magnified onto the wall: station 0 is 1.1 m from the box's face
// and 3.8 m from the wall y = 5 (×3.45), which moves the edge by up to 0.086 m; with half a
// vossel more, "away from the edge" means farther than kEdgeBandM from the analytic edge.
constexpr double kEdgeBandM = 0.12;

class VisibilityTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    room_ = new scenes::SyntheticRoom(scenes::SyntheticRoom::Default());
    scenes::LidarSettings settings;
    settings.azimuth_steps = 1440;
    settings.elevation_steps = 720;
    auto g = BuildGeometry(scenes::StationLidars(*room_, settings), kVosselM);
    ASSERT_TRUE(g.ok()) << g.status();
    geometry_ = new records::VosselGeometry(std::move(*g));
    for (int s = 0; s < 2; ++s) {
      const geometry::Pose pose = room_->Stations()[s];
      const double pitch = 2.0 * M_PI / settings.azimuth_steps;
      DepthPanorama depth = RenderDepthPanorama(*geometry_, pose, DepthPanoramaSize(pitch), 0.3e-3);
      vis_[s] = new std::vector<float>(ComputeVisibility(*geometry_, depth, DepthToleranceM(kVosselM)));
    }
  }
  static void TearDownTestSuite() {
    delete room_;
    delete geometry_;
    delete vis_[0];
    delete vis_[1];
  }

  // Vossel index holding world point x, or -1.
  static int32_t VosselAt(const Eigen::Vector3d& x) {
    const openvdb::Coord c(int(std::round(x.x() / kVosselM)), int(std::round(x.y() / kVosselM)),
                           int(std::round(x.z() / kVosselM)));
    int32_t k = -1;
    geometry_->index_grid->tree().probeValue(c, k);
    return k;
  }

  // Analytic share of a vossel's surface patch (5×5 points over side h in the face plane, the
  // same footprint the PCF uses) visible from o.
  static double AnalyticShare(const Eigen::Vector3d& x, const Eigen::Vector3d& n, const Eigen::Vector3d& o,
                              double side_m, int grid) {
    const Eigen::Vector3d a = std::abs(n.x()) < 0.9 ? Eigen::Vector3d::UnitX() : Eigen::Vector3d::UnitY();
    const Eigen::Vector3d t1 = n.cross(a).normalized(), t2 = n.cross(t1);
    int visible = 0;
    for (int i = 0; i < grid; ++i)
      for (int j = 0; j < grid; ++j) {
        const Eigen::Vector3d p = x + ((i + 0.5) / grid - 0.5) * side_m * t1 + ((j + 0.5) / grid - 0.5) * side_m * t2;
        visible += room_->Visible(o, p, 1e-4) ? 1 : 0;
      }
    return double(visible) / (grid * grid);
  }

  static scenes::SyntheticRoom* room_;
  static records::VosselGeometry* geometry_;
  static std::vector<float>* vis_[2];
};
scenes::SyntheticRoom* VisibilityTest::room_ = nullptr;
records::VosselGeometry* VisibilityTest::geometry_ = nullptr;
std::vector<float>* VisibilityTest::vis_[2] = {nullptr, nullptr};

// Claim (§5): the slope-scaled tolerance τ_k = τ + r·Δ·tanθ is τ at normal incidence, also
// when |n·v| of a float normal rounds past 1 (it was NaN there, and every sample of such a
// vossel failed its test: V = 0 for a surface facing the sensor head on); at grazing incidence
// it takes cosθ's floor.
TEST(SlopeScaledToleranceTest, IsTauHeadOnAndFiniteWhenTheCosineRoundsPastOne) {
  const double tau = 0.075, r = 3.5, pixel = 0.0085;
  EXPECT_DOUBLE_EQ(SlopeScaledToleranceM(tau, r, pixel, 1.0), tau);
  EXPECT_DOUBLE_EQ(SlopeScaledToleranceM(tau, r, pixel, std::nextafter(1.0, 2.0)), tau);
  EXPECT_DOUBLE_EQ(SlopeScaledToleranceM(tau, r, pixel, 1.0 + 1e-7), tau);
  const double c = geometry::kCosIncidenceMin;
  EXPECT_DOUBLE_EQ(SlopeScaledToleranceM(tau, r, pixel, 0.0),
                   tau + r * pixel * std::sqrt(1.0 - c * c) / c);
}

// Claim (§5): behind the box, shadow from station 0 and lit from station 1; ≥ 98% right.
TEST_F(VisibilityTest, ShadowBehindOccluderLitFromOtherStation) {
  const geometry::Pose s0 = room_->Stations()[0];
  const geometry::Pose s1 = room_->Stations()[1];
  const std::vector<Eigen::Vector3d> shadow = room_->FaceSamples(
      scenes::kFaceWallYMax, 0.1, kEdgeBandM, {s1.o_world}, {s0.o_world});
  ASSERT_GT(shadow.size(), 20u) << "the scene must have a shadow region";
  int found = 0, right = 0;
  for (const Eigen::Vector3d& x : shadow) {
    const int32_t k = VosselAt(x);
    if (k < 0) continue;
    ++found;
    if ((*vis_[0])[k] == 0.0f && (*vis_[1])[k] == 1.0f) ++right;
  }
  std::printf("shadow region: %d of %d samples have a vossel; %d (%.2f%%) are shadow from station 0 "
              "and lit from station 1\n", found, int(shadow.size()), right, 100.0 * right / found);
  EXPECT_GT(found, int(shadow.size() * 0.9)) << "station 1 must have placed vossels in the shadow region";
  EXPECT_GE(double(right) / found, 0.98);

  const std::vector<Eigen::Vector3d> lit = room_->FaceSamples(
      scenes::kFaceWallYMax, 0.1, kEdgeBandM, {s0.o_world, s1.o_world}, {});
  int lit_found = 0, lit_right = 0;
  for (const Eigen::Vector3d& x : lit) {
    const int32_t k = VosselAt(x);
    if (k < 0) continue;
    ++lit_found;
    if ((*vis_[0])[k] == 1.0f && (*vis_[1])[k] == 1.0f) ++lit_right;
  }
  std::printf("control region: %d (%.2f%%) of %d vossels lit from both stations\n", lit_right,
              100.0 * lit_right / lit_found, lit_found);
  EXPECT_GE(double(lit_right) / lit_found, 0.98);
}

// Claim (§5): compared with the analytic answer, vossels away from the shadow's edge are
// classified right (≥ 98%) on the floor and on the wall behind the box, and vossels on the edge
// of the shadow the box casts on the floor are penumbra (0 < V < 1). On the far wall the §5
// dilation moves the edge by up to 0.15 m (see kEdgeBandM), so edge vossels are judged on the
// floor, where the box stands and the shift is a fraction of a vossel.
TEST_F(VisibilityTest, AgreesWithAnalyticAnswerAndEdgesArePenumbra) {
  const Eigen::Vector3d o = room_->Stations()[0].o_world;
  struct Face {
    const char* name;
    int face;
    int axis;       // the axis the face is perpendicular to
    double at_m;    // its coordinate
  };
  const Face faces[] = {{"floor", scenes::kFaceFloor, 2, room_->RoomBounds().min_m.z()},
                        {"wall behind the box", scenes::kFaceWallYMax, 1, room_->RoomBounds().max_m.y()}};
  const Aabb& room = room_->RoomBounds();
  const Aabb& box = room_->OccluderBounds();
  for (const Face& f : faces) {
    const Eigen::Vector3d n = scenes::SyntheticRoom::FaceNormal(f.face);
    int away = 0, away_right = 0, edge = 0, edge_fractional = 0, edge_graded = 0;
    for (size_t k = 0; k < geometry_->size(); ++k) {
      Eigen::Vector3d x = geometry_->centroid_m[k].cast<double>();
      if (std::abs(x[f.axis] - f.at_m) > 0.01) continue;  // this face's vossels only
      x[f.axis] = f.at_m;  // on the analytic face, not at the noisy centroid
      bool near_border = false;  // room corners and the box's footprint on the floor
      for (int a = 0; a < 3; ++a) {
        if (a == f.axis) continue;
        near_border |= x[a] < room.min_m[a] + 0.1 || x[a] > room.max_m[a] - 0.1;
      }
      if (f.face == scenes::kFaceFloor) {
        near_border |= x.x() > box.min_m.x() - 0.1 && x.x() < box.max_m.x() + 0.1 &&
                       x.y() > box.min_m.y() - 0.1 && x.y() < box.max_m.y() + 0.1;
      }
      if (near_border) continue;
      const float v = (*vis_[0])[k];
      // "Away from edges": the analytic answer is the same over a patch 2·kEdgeBandM wide.
      const double wide = AnalyticShare(x, n, o, 2 * kEdgeBandM, 9);
      if (wide == 1.0 || wide == 0.0) {
        ++away;
        away_right += (wide == 1.0) == (v == 1.0f) && (wide == 0.0) == (v == 0.0f);
      }
      // On the edge: the analytic share over the vossel's own PCF patch is strictly fractional.
      const double own = AnalyticShare(x, n, o, 0.8 * kVosselM, 9);
      if (own > 0.05 && own < 0.95) {
        ++edge;
        edge_fractional += v > 0.0f && v < 1.0f;
        // The lattice quantises the occluder to whole vossels, which moves its shadow's edge by
        // up to half a vossel (magnified): count the edge as graded when a penumbra vossel lies
        // within one vossel of it in the face plane.
        bool graded = false;
        const openvdb::Coord c = geometry_->coord[k];
        for (int du = -1; du <= 1; ++du)
          for (int dv = -1; dv <= 1; ++dv) {
            openvdb::Coord q = c;
            q[(f.axis + 1) % 3] += du;
            q[(f.axis + 2) % 3] += dv;
            int32_t j;
            if (geometry_->index_grid->tree().probeValue(q, j)) {
              graded |= (*vis_[0])[j] > 0.0f && (*vis_[0])[j] < 1.0f;
            }
          }
        edge_graded += graded;
      }
    }
    std::printf("%s from station 0: %d of %d vossels away from edges classified right (%.2f%%); "
                "of %d vossels on the analytic edge, %d are penumbra (0 < V < 1) and %d have a "
                "penumbra vossel within one vossel\n",
                f.name, away_right, away, 100.0 * away_right / away, edge, edge_fractional, edge_graded);
    ASSERT_GT(away, 1000);
    EXPECT_GE(double(away_right) / away, 0.98);
    if (f.face == scenes::kFaceFloor) {
      ASSERT_GT(edge, 10);
      EXPECT_GE(double(edge_fractional) / edge, 0.3);
      EXPECT_GE(double(edge_graded) / edge, 0.9);
    }
  }
}

}  // namespace
}  // namespace vasl::ingest

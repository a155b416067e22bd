// VASL-MODEL §8 view term: with η > 0 a render favours the records of scans that saw a vossel
// from near the render's own direction; η = 0 is the fused colour C_k.
#include <cmath>

#include <gtest/gtest.h>

#include "lattice/fusion/fuse.h"
#include "lattice/records/record_grid.h"
#include "lattice/render/render.h"

namespace vasl::render {
namespace {

constexpr double kVosselM = 0.05;

// A floor patch (z = 0, normal +z) of 40×40 vossels, each seen by two cameras: source 0 low in
// the west (red) and source 1 high overhead (blue), with equal weights.
struct TwoViewFloor {
  records::VosselGeometry geometry;
  records::RecordSet records;
  records::FusedValues fused;
  Eigen::Vector3d west{-3.0, 1.0, 2.0}, top{1.0, 1.0, 6.0};
};

TwoViewFloor MakeFloor() {
  TwoViewFloor f;
  f.geometry.vossel_size_m = kVosselM;
  for (int i = 0; i < 40; ++i)
    for (int j = 0; j < 40; ++j) f.geometry.coord.emplace_back(i, j, 0);
  records::CanonicalizeVosselOrder(f.geometry);
  const size_t n = f.geometry.size();
  f.geometry.point_count.assign(n, 10);
  f.geometry.normal.assign(n, Eigen::Vector3f::UnitZ());
  f.geometry.covariance_m2.assign(n, {});
  for (size_t k = 0; k < n; ++k) {
    const openvdb::Coord c = f.geometry.coord[k];
    f.geometry.centroid_m.emplace_back(float(c.x() * kVosselM), float(c.y() * kVosselM), 0.0f);
  }
  const float red[3] = {0.9f, 0.1f, 0.1f}, blue[3] = {0.1f, 0.1f, 0.9f};
  for (size_t k = 0; k < n; ++k) {
    for (int src = 0; src < 2; ++src) {
      const size_t i = f.records.size();
      f.records.Resize(i + 1);
      f.records.vossel[i] = int32_t(k);
      f.records.scan[i] = src;
      f.records.modality[i] = int8_t(records::Modality::kRgb);
      for (int c = 0; c < 3; ++c) f.records.value[3 * i + c] = (src == 0 ? red : blue)[c];
      f.records.range_m[i] = 4.0f;
      f.records.cos_inc[i] = 1.0f;  // equal weights: the test is about the view term alone
      f.records.foot_major_m[i] = f.records.foot_minor_m[i] = 0.001f;
      f.records.vis[i] = 1.0f;
      for (int c = 0; c < 4; ++c) f.records.conf[4 * i + c] = 1.0f;
      f.records.flags[i] = 0;
      f.records.batch[i] = 1;
    }
  }
  f.fused = *fusion::Fuse(f.records, n, kVosselM, fusion::WeightingProfile{});
  return f;
}

// Mean rendered colour over hit pixels, and the hit count.
Eigen::Vector3d MeanColour(const RenderImage& image, int64_t* hits) {
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  *hits = 0;
  for (size_t p = 0; p < image.depth_m.size(); ++p) {
    if (!std::isfinite(image.depth_m[p])) continue;
    ++*hits;
    sum += Eigen::Vector3d(image.rgb[3 * p], image.rgb[3 * p + 1], image.rgb[3 * p + 2]);
  }
  return sum / double(std::max<int64_t>(*hits, 1));
}

TEST(ViewBlendTest, ViewTermFavoursScansSeenFromNearTheRenderDirection) {
  const TwoViewFloor f = MakeFloor();
  auto weights = fusion::RecordWeights(f.records, f.geometry.size(), kVosselM, fusion::WeightingProfile{});
  ASSERT_TRUE(weights.ok());
  ViewBlendInputs blend;
  blend.records = &f.records;
  blend.weight = &weights->weight;
  blend.begin = &weights->begin;
  blend.source_origin_m = {f.west, f.top};

  RenderRequest req;
  req.width_px = 512;
  req.height_px = 256;
  req.pose.o_world = Eigen::Vector3d(-2.0, 1.0, 1.5);  // near the west camera
  // η = 0: the fused colour, the even mix of red and blue.
  auto flat = RenderEquirect(f.geometry, f.fused, req, &blend);
  ASSERT_TRUE(flat.ok()) << flat.status();
  int64_t hits = 0;
  const Eigen::Vector3d mix = MeanColour(*flat, &hits);
  ASSERT_GT(hits, 100);
  EXPECT_NEAR(mix.x(), 0.5, 1e-5);
  EXPECT_NEAR(mix.z(), 0.5, 1e-5);
  // η = 8 from the west: the west (red) records dominate; from overhead, the blue ones.
  req.eta = 8.0;
  auto west = RenderEquirect(f.geometry, f.fused, req, &blend);
  ASSERT_TRUE(west.ok()) << west.status();
  const Eigen::Vector3d from_west = MeanColour(*west, &hits);
  req.pose.o_world = Eigen::Vector3d(1.0, 1.0, 5.0);
  auto top = RenderEquirect(f.geometry, f.fused, req, &blend);
  ASSERT_TRUE(top.ok());
  const Eigen::Vector3d from_top = MeanColour(*top, &hits);
  std::printf("η = 8: mean colour seen from the west (%.3f %.3f %.3f), from overhead (%.3f %.3f "
              "%.3f); η = 0: (%.3f %.3f %.3f)\n", from_west.x(), from_west.y(), from_west.z(),
              from_top.x(), from_top.y(), from_top.z(), mix.x(), mix.y(), mix.z());
  EXPECT_GT(from_west.x(), 0.7);
  EXPECT_LT(from_west.z(), 0.3);
  EXPECT_GT(from_top.z(), 0.7);
  EXPECT_LT(from_top.x(), 0.3);
  // Larger η sharpens the preference monotonically.
  req.pose.o_world = Eigen::Vector3d(-2.0, 1.0, 1.5);
  req.eta = 2.0;
  const Eigen::Vector3d mild = MeanColour(*RenderEquirect(f.geometry, f.fused, req, &blend), &hits);
  std::printf("η = 2 from the west: red %.3f (η = 8: %.3f)\n", mild.x(), from_west.x());
  EXPECT_GT(mild.x(), 0.5);
  EXPECT_LT(mild.x(), from_west.x());
}

TEST(ViewBlendTest, EtaNeedsTheRecords) {
  const TwoViewFloor f = MakeFloor();
  RenderRequest req;
  req.width_px = 64;
  req.height_px = 32;
  req.eta = 1.0;
  EXPECT_EQ(RenderEquirect(f.geometry, f.fused, req).status().code(),
            absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace vasl::render

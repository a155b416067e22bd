// VASL-MODEL §5 on the corridor site, where the walls near a sensor hide most of the lattice:
// the shortcuts of the visibility test give the same answer as the plain computation.
// Visibility with the shadow-by-cells test equals the sample-by-sample test; the depth panorama
// culled front to back equals the min of unculled ones; the separable dilation equals a
// brute-force min over its window.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <random>

#include <gtest/gtest.h>

#include "lattice/geometry/equirect.h"
#include "lattice/geometry/footprint.h"
#include "lattice/ingest/visibility.h"
#include "lattice/ingest/voxelise.h"
#include "lattice/memory/isa.h"
#include "tests/scenes/corridor_lattice.h"

namespace vasl::ingest {
namespace {

// The corridor's lattice, and the vossel size it was built at.
using VisibilityShortcutTest = scenes::CorridorLatticeTest;
constexpr double kVosselM = scenes::CorridorLatticeTest::kVosselM;

// Claim: V from the shadow-by-cells test equals V tested sample by sample (the vossels tested
// in chunks below kShadowByCellsMinVossels), on the raw and on a dilated panorama, and most of
// the site is in shadow from one station (so the shortcut is taken for most vossels).
TEST_F(VisibilityShortcutTest, ShadowByCellsEqualsSampleTests) {
  const size_t n = geometry_->size();
  const geometry::Pose pose = site_->Stations()[4];
  for (int dilate : {0, 2}) {
    DepthPanorama depth =
        RenderDepthPanorama(*geometry_, pose, DepthPanoramaSize(2.0 * M_PI / 1024), 0.3e-3);
    DilateDepthPanorama(depth, dilate);
    const double tau = DepthToleranceM(kVosselM);
    const std::vector<float> all = ComputeVisibility(*geometry_, depth, tau, nullptr, 1 + dilate);
    std::vector<float> chunked(n, 0.0f);
    const size_t chunk = kShadowByCellsMinVossels - 1;
    for (size_t begin = 0; begin < n; begin += chunk) {
      std::vector<uint8_t> only(n, 0);
      std::fill(only.begin() + begin, only.begin() + std::min(n, begin + chunk), 1);
      const std::vector<float> part = ComputeVisibility(*geometry_, depth, tau, &only, 1 + dilate);
      std::copy(part.begin() + begin, part.begin() + std::min(n, begin + chunk),
                chunked.begin() + begin);
    }
    size_t differ = 0, shadow = 0, lit = 0;
    for (size_t k = 0; k < n; ++k) {
      differ += all[k] != chunked[k] ? 1 : 0;
      shadow += all[k] == 0.0f ? 1 : 0;
      lit += all[k] == 1.0f ? 1 : 0;
    }
    std::printf("dilation %d px: %zu vossels, %zu in shadow, %zu lit, %zu differ\n", dilate, n,
                shadow, lit, differ);
    EXPECT_EQ(differ, 0u);
    EXPECT_GT(shadow, n / 2);
    EXPECT_GT(lit, n / 20);
  }
}

// Claim (ComputeVisibility, `only`): a vossel flagged (any nonzero flag) gets the V of the
// unmasked computation and every other vossel 0, for a scattered mask as a revisit's: lone
// flags, short runs and long gaps, enough of them that the shadow-by-cells chunks are taken,
// and chunks entered at a flag past their first vossel.
TEST_F(VisibilityShortcutTest, AScatteredMaskTestsExactlyItsVossels) {
  const size_t n = geometry_->size();
  const geometry::Pose pose = site_->Stations()[4];
  DepthPanorama depth =
      RenderDepthPanorama(*geometry_, pose, DepthPanoramaSize(2.0 * M_PI / 1024), 0.3e-3);
  const double tau = DepthToleranceM(kVosselM);
  const std::vector<float> all = ComputeVisibility(*geometry_, depth, tau, nullptr, 1);
  std::mt19937_64 rng(17);
  std::vector<uint8_t> only(n, 0);
  size_t flagged = 0;
  for (size_t k = 0; k < n;) {
    const size_t gap = rng() % 4 == 0 ? rng() % 300 : rng() % 9;  // long gaps and short ones
    k += gap;
    const size_t run = 1 + rng() % 5;
    for (size_t e = k; e < std::min(n, k + run); ++e, ++flagged) {
      only[e] = uint8_t(1 + rng() % 3);  // flags other than 1 count as set
    }
    k += run;
  }
  ASSERT_GE(flagged, kShadowByCellsMinVossels);
  ASSERT_LT(flagged, n / 2);
  const std::vector<float> part = ComputeVisibility(*geometry_, depth, tau, &only, 1);
  size_t differ = 0, unflagged_nonzero = 0, tested_nonzero = 0;
  for (size_t k = 0; k < n; ++k) {
    if (only[k]) {
      differ += part[k] != all[k] ? 1 : 0;
      tested_nonzero += part[k] > 0.0f ? 1 : 0;
    } else {
      unflagged_nonzero += part[k] != 0.0f ? 1 : 0;
    }
  }
  std::printf("%zu of %zu vossels flagged, %zu of them with V > 0\n", flagged, n, tested_nonzero);
  EXPECT_EQ(differ, 0u);
  EXPECT_EQ(unflagged_nonzero, 0u);
  EXPECT_GT(tested_nonzero, flagged / 50);  // some flagged vossels are lit: not all shadow
}

// Claim (a panorama that does not depend on the machine): the depth panorama splatted by the
// baseline's instruction set and by every wider one this CPU runs (memory/isa.h) is the same
// bits, pixel for pixel, from three stations and at a camera's and a LiDAR's splat growth.
TEST_F(VisibilityShortcutTest, EveryInstructionSetSplatsTheSameBits) {
  const geometry::EquirectSize size = DepthPanoramaSize(2.0 * M_PI / 1024);
  int compared = 0;
  for (size_t station : {0, 4, 9}) {
    for (double divergence : {0.3e-3, 2.0 * M_PI / 1024}) {
      const geometry::Pose pose = site_->Stations()[station];
      memory::SetIsaCap(memory::Isa::kBaseline);
      const DepthPanorama baseline = RenderDepthPanorama(*geometry_, pose, size, divergence);
      for (memory::Isa isa : {memory::Isa::kAvx2, memory::Isa::kX86_64_V4}) {
        if (!memory::Supports(isa)) continue;
        memory::SetIsaCap(isa);
        const DepthPanorama wider = RenderDepthPanorama(*geometry_, pose, size, divergence);
        size_t differ = 0;
        for (size_t p = 0; p < baseline.depth_m.size(); ++p) {
          differ += std::memcmp(&baseline.depth_m[p], &wider.depth_m[p], sizeof(float)) != 0;
        }
        EXPECT_EQ(differ, 0u) << "station " << station << ", instruction set " << int(isa);
        ++compared;
      }
    }
  }
  memory::SetIsaCap(memory::Isa::kX86_64_V4);
  std::printf("depth panoramas of wider instruction sets compared bit for bit with the "
              "baseline's: %d\n", compared);
}

// Claim (the same V on every machine): ComputeVisibility, which projects a vossel's 16 grid
// samples in vectors (two, four or eight lanes by instruction set, geometry::Atan2's branches
// as selects), counts for every vossel exactly the samples the scalar projection
// (geometry::EquirectProject, the formula of §5 sample by sample) finds lit: from three
// stations, under every instruction set this CPU runs, one of them on the vertical through a
// vossel (its samples about the sensor's axis, in every octant).
TEST_F(VisibilityShortcutTest, GridSamplesCountAsTheScalarSamples) {
  const size_t n = geometry_->size();
  const double h = kVosselM, tau = DepthToleranceM(kVosselM);
  const int slope_pixels = 1;
  size_t compared = 0, partly_lit = 0;
  for (size_t station : {0, 4, 9}) {
    geometry::Pose pose = site_->Stations()[station];
    if (station == 9) {  // on the vertical through a vossel's centroid: samples on the axis
      pose.o_world.x() = double(geometry_->FrameCentroid(n / 2).x());
      pose.o_world.y() = double(geometry_->FrameCentroid(n / 2).y());
    }
    const DepthPanorama depth =
        RenderDepthPanorama(*geometry_, pose, DepthPanoramaSize(2.0 * M_PI / 1024), 0.3e-3);
    const int W = depth.size.width_px, H = depth.size.height_px;
    const Eigen::Matrix3d R = pose.q_world_sensor.conjugate().toRotationMatrix();
    const double pixel_rad = slope_pixels * std::max(geometry::AzimuthPitchRad(depth.size),
                                                     geometry::ElevationPitchRad(depth.size));
    std::vector<float> want(n, 0.0f);
    for (size_t k = 0; k < n; ++k) {
      const Eigen::Vector3d x = geometry_->FrameCentroid(k).cast<double>();
      Eigen::Vector3d normal = geometry_->FrameNormal(k).cast<double>();
      const Eigen::Vector3d to_sensor = pose.o_world - x;
      if (to_sensor.squaredNorm() == 0.0) continue;
      if (normal.squaredNorm() < 0.5) normal = to_sensor.normalized();
      const double tolerance = VosselToleranceM(tau, to_sensor, normal, pixel_rad);
      const Eigen::Vector3d t1 = geometry::AnyTangent(normal), t2 = normal.cross(t1);
      int lit = 0;
      for (int s = 0; s < 17; ++s) {  // the 4×4 grid, then the centre
        const double sa = s == 16 ? 0.0 : ((s / 4 + 0.5) / 4 - 0.5) * h;
        const double sb = s == 16 ? 0.0 : ((s % 4 + 0.5) / 4 - 0.5) * h;
        const Eigen::Vector3d p = R * (x + sa * t1 + sb * t2 - pose.o_world);
        const Eigen::Vector2d uv = geometry::EquirectProject(p, depth.size);
        const int i = geometry::WrapColumn(int(std::floor(uv.x())), W);
        const int j = std::clamp(int(std::floor(uv.y())), 0, H - 1);
        lit += depth.At(i, j) >= p.norm() - tolerance ? 1 : 0;
      }
      want[k] = float(lit) / 17.0f;
      partly_lit += lit > 0 && lit < 17 ? 1 : 0;
    }
    for (memory::Isa isa : {memory::Isa::kBaseline, memory::Isa::kAvx2, memory::Isa::kX86_64_V4}) {
      if (!memory::Supports(isa)) continue;
      memory::SetIsaCap(isa);
      const std::vector<float> got =
          ComputeVisibility(*geometry_, depth, tau, nullptr, slope_pixels,
                            /*shadow_by_cells=*/false);
      size_t differ = 0;
      for (size_t k = 0; k < n; ++k) differ += got[k] != want[k] ? 1 : 0;
      EXPECT_EQ(differ, 0u) << "station " << station << ", instruction set " << int(isa);
      compared += n;
    }
  }
  memory::SetIsaCap(memory::Isa::kX86_64_V4);
  std::printf("vossels whose lit samples were counted as the scalar projection counts them: "
              "%zu (%zu partly lit)\n", compared, partly_lit);
  EXPECT_GT(partly_lit, 100u);  // counts that a sample's pixel decides
}

// Claim: the front-to-back culling of RenderDepthPanorama (taken from kCullMinVossels splatted
// vossels) leaves the panorama as it is: the panorama of every vossel equals, pixel for pixel,
// the min over panoramas of chunks too small to be culled; and with reach cells flagged it
// equals that panorama on the flagged cells (+inf elsewhere). Most of the site lies behind
// nearer walls from one station, so the culling is taken for many blocks.
TEST_F(VisibilityShortcutTest, FrontToBackCullingKeepsThePanorama) {
  const size_t n = geometry_->size();
  ASSERT_GE(n, 4 * kCullMinVossels);
  const geometry::Pose pose = site_->Stations()[4];
  const geometry::EquirectSize size = DepthPanoramaSize(2.0 * M_PI / 1024);
  const double divergence = 0.3e-3;
  const DepthPanorama culled = RenderDepthPanorama(*geometry_, pose, size, divergence);
  std::vector<float> merged(culled.depth_m.size(), INFINITY);
  const size_t chunk = kCullMinVossels - 1;
  for (size_t begin = 0; begin < n; begin += chunk) {
    std::vector<uint8_t> only(n, 0);
    std::fill(only.begin() + begin, only.begin() + std::min(n, begin + chunk), 1);
    const DepthPanorama part = RenderDepthPanorama(*geometry_, pose, size, divergence, &only);
    for (size_t p = 0; p < merged.size(); ++p) merged[p] = std::min(merged[p], part.depth_m[p]);
  }
  size_t differ = 0, finite = 0;
  for (size_t p = 0; p < merged.size(); ++p) {
    differ += culled.depth_m[p] != merged[p] ? 1 : 0;
    finite += std::isfinite(merged[p]) ? 1 : 0;
  }
  std::printf("%zu pixels, %zu with depth, %zu differ\n", merged.size(), finite, differ);
  EXPECT_EQ(differ, 0u);
  EXPECT_GT(finite, merged.size() / 2);

  // Flagged cells: every third one, and (as a revisit's) a small patch of them alone, where
  // whole blocks are passed over by the flagged cells and the culling reads those cells alone.
  constexpr int kCell = tiles::kReachBlockPx;
  const int cells_w = size.width_px / kCell, cells_h = size.height_px / kCell;
  const tiles::ReachRaster reach_all = tiles::ReachFromDepth(merged, size);
  std::vector<uint8_t> every_third(size_t(cells_w) * cells_h, 0), patch = every_third;
  for (size_t c = 0; c < every_third.size(); c += 3) every_third[c] = 1;
  for (int cj = cells_h / 2 - 2; cj < cells_h / 2 + 2; ++cj) {
    for (int ci = 5; ci < 11; ++ci) patch[size_t(cj) * cells_w + ci] = 1;
  }
  for (const std::vector<uint8_t>* cells : {&every_third, &patch}) {
    const DepthPanorama within =
        RenderDepthPanorama(*geometry_, pose, size, divergence, nullptr, cells);
    size_t wrong = 0, outside_rows = 0, flagged_finite = 0;
    for (int j = 0; j < size.height_px; ++j) {
      for (int i = 0; i < size.width_px; ++i) {
        const bool flagged = (*cells)[size_t(j / kCell) * cells_w + i / kCell] != 0;
        const float want = flagged ? merged[size_t(j) * size.width_px + i] : INFINITY;
        wrong += within.At(i, j) != want ? 1 : 0;
        flagged_finite += flagged && std::isfinite(want) ? 1 : 0;
        const bool in_rows = j >= within.splat_row_begin && j < within.splat_row_end;
        outside_rows += !in_rows && std::isfinite(within.At(i, j)) ? 1 : 0;
      }
    }
    // The reach of the flagged cells alone: the whole one's there, `elsewhere` in the others.
    const tiles::ReachRaster reach = tiles::ReachFromDepth(within.depth_m, size, cells, -1.0f);
    size_t reach_wrong = 0;
    for (size_t c = 0; c < cells->size(); ++c) {
      reach_wrong += reach.max_depth_m[c] != ((*cells)[c] ? reach_all.max_depth_m[c] : -1.0f);
    }
    std::printf("%zu flagged cells: %zu flagged pixels with depth, %zu differ, rows %d-%d\n",
                size_t(std::count(cells->begin(), cells->end(), uint8_t{1})), flagged_finite,
                wrong, within.splat_row_begin, within.splat_row_end);
    EXPECT_EQ(wrong, 0u);
    EXPECT_GT(flagged_finite, 0u);
    EXPECT_EQ(outside_rows, 0u);
    EXPECT_EQ(reach_wrong, 0u);
  }
}

// Claim: the dilation is the min over the (2r+1)² window, columns wrapping at the seam and rows
// clamped at the poles, on the rows asked for; the other rows keep their depth.
TEST(DilateDepthPanorama, IsTheMinOverItsWindow) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> u(0.5f, 20.0f);
  DepthPanorama depth;
  depth.size = {64, 32};
  depth.depth_m.resize(64 * 32);
  for (float& d : depth.depth_m) d = (rng() % 5 == 0) ? INFINITY : u(rng);
  for (int r : {1, 2, 3}) {
    for (auto [begin, end] : {std::pair{0, 32}, std::pair{0, 3}, std::pair{10, 17}, std::pair{29, 32}}) {
      DepthPanorama out = depth;
      DilateDepthPanorama(out, r, begin, end);
      int wrong = 0;
      for (int j = 0; j < 32; ++j) {
        for (int i = 0; i < 64; ++i) {
          float want = depth.At(i, j);
          if (j >= begin && j < end) {
            for (int dj = -r; dj <= r; ++dj) {
              for (int di = -r; di <= r; ++di) {
                want = std::min(want, depth.At((i + di + 64) % 64, std::clamp(j + dj, 0, 31)));
              }
            }
          }
          wrong += out.At(i, j) != want ? 1 : 0;
        }
      }
      EXPECT_EQ(wrong, 0) << "radius " << r << ", rows [" << begin << ", " << end << ")";
    }
  }
}

}  // namespace
}  // namespace vasl::ingest

// The reach raster decides which (source, block) pairs an ingest revisits (VASL-MODEL §5: "only
// for (scan, region) pairs whose depth panorama the new geometry changes"), so it must never
// say "hidden" where a pixel of the depth panorama says "reaches". These tests check that claim
// pixel by pixel, on depth panoramas of every size DepthPanoramaSize gives (its cells must line
// up with the pixels they bin), and the cell coverage a revisit merges its raster by.
#include "lattice/tiles/tiling.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>
#include <string>
#include <utility>

#include <Eigen/Geometry>

#include <gtest/gtest.h>

#include "lattice/ingest/visibility.h"

namespace vasl::tiles {
namespace {

Eigen::Vector3d PixelDirection(int i, int j, const geometry::EquirectSize& size) {
  const double phi = 2.0 * M_PI * (0.5 - (i + 0.5) / size.width_px);
  const double psi = M_PI * (0.5 - (j + 0.5) / size.height_px);
  return {std::cos(psi) * std::cos(phi), std::cos(psi) * std::sin(phi), std::sin(psi)};
}

// A random sensor pose, so that the caps are tested in a rotated sensor frame too.
geometry::Pose RandomPose(std::mt19937& rng) {
  std::normal_distribution<double> n(0.0, 1.0);
  geometry::Pose pose;
  pose.o_world = Eigen::Vector3d(n(rng), n(rng), n(rng));
  pose.q_world_sensor = Eigen::Quaterniond(n(rng), n(rng), n(rng), n(rng)).normalized();
  return pose;
}

ViewCap RandomCap(std::mt19937& rng) {
  std::normal_distribution<double> n(0.0, 1.0);
  std::uniform_real_distribution<double> angle(0.002, 0.2);
  ViewCap cap;
  cap.dir = Eigen::Vector3d(n(rng), n(rng), n(rng)).normalized();
  cap.half_angle_rad = angle(rng);
  return cap;
}

TEST(DepthPanoramaSize, CellsLineUpWithPixels) {
  // ReachFromDepth bins kReachBlockPx² pixels per cell, and Reaches and CellCoverage place
  // cell c at the angles of its pixels only when the panorama's rows and columns are whole
  // multiples of the cell: every size the depth panoramas take must be.
  for (double pitch = 2e-4; pitch < 0.2; pitch *= 1.013) {
    const geometry::EquirectSize size = ingest::DepthPanoramaSize(pitch);
    EXPECT_EQ(size.height_px % kReachBlockPx, 0) << "pitch " << pitch;
    EXPECT_EQ(size.width_px, 2 * size.height_px) << "pitch " << pitch;
    // Within half a cell of the asked pitch (a cell is 16 pixels), clamped to [32, 2048] rows.
    const double rows = std::clamp(M_PI / pitch, 32.0, 2048.0);
    EXPECT_LE(std::abs(size.height_px - rows), 0.5 * kReachBlockPx + 1e-9) << "pitch " << pitch;
  }
}

TEST(ReachRaster, CellsHoldTheMaxAndMinOfTheirPixels) {
  // ReachFromDepth's max and CellMinFromDepth's min per cell, against a loop over each cell's
  // pixels: on whole cells, on a size with partial cells at the right and bottom edges, and
  // with CellMinFromDepth's rows restricted (rows outside count as +inf).
  std::mt19937 rng(11);
  std::uniform_real_distribution<float> u(0.5f, 20.0f), coin(0.0f, 1.0f);
  const float inf = std::numeric_limits<float>::infinity();
  for (const geometry::EquirectSize size :
       {geometry::EquirectSize{256, 128}, geometry::EquirectSize{200, 75}}) {
    std::vector<float> depth_m(size_t(size.width_px) * size.height_px);
    for (float& d : depth_m) d = coin(rng) < 0.1f ? inf : u(rng);
    const ReachRaster reach = ReachFromDepth(depth_m, size);
    for (const auto [row_begin, row_end] :
         {std::pair<int, int>{0, -1}, {5, 40}, {17, 18}, {40, 40}}) {
      const std::vector<float> mins = CellMinFromDepth(depth_m, size, row_begin, row_end);
      ASSERT_EQ(mins.size(), reach.max_depth_m.size());
      const int rows_end = row_end < 0 ? size.height_px : row_end;
      for (int cj = 0; cj < reach.size.height_px; ++cj) {
        for (int ci = 0; ci < reach.size.width_px; ++ci) {
          float most = -inf, least = inf;
          for (int j = cj * kReachBlockPx; j < std::min(size.height_px, (cj + 1) * kReachBlockPx);
               ++j) {
            for (int i = ci * kReachBlockPx;
                 i < std::min(size.width_px, (ci + 1) * kReachBlockPx); ++i) {
              const float d = depth_m[size_t(j) * size.width_px + i];
              most = std::max(most, d);
              if (j >= row_begin && j < rows_end) least = std::min(least, d);
            }
          }
          const size_t c = size_t(cj) * reach.size.width_px + ci;
          EXPECT_EQ(reach.max_depth_m[c], most) << "cell " << ci << "," << cj;
          EXPECT_EQ(mins[c], least) << "cell " << ci << "," << cj << " rows " << row_begin;
        }
      }
    }
  }
}

TEST(ReachRaster, NeverHidesAPixelThatReaches) {
  std::mt19937 rng(7);
  // A near wall everywhere, with a few deep pixels (doorways): a cell's bound is deep only
  // where one of its own pixels is, so a cell placed at the wrong angles shows.
  std::uniform_real_distribution<float> deep(5.0f, 10.0f), u(0.0f, 1.0f);
  int reaching = 0, checked = 0;
  for (double pitch : {0.0123, 0.0031, 0.0047, 0.0081}) {
    const geometry::EquirectSize size = ingest::DepthPanoramaSize(pitch);
    std::vector<float> depth_m(size_t(size.width_px) * size.height_px);
    for (float& d : depth_m) d = u(rng) < 0.002f ? deep(rng) : 1.0f;
    const ReachRaster reach = ReachFromDepth(depth_m, size);
    for (int trial = 0; trial < 400; ++trial) {
      const geometry::Pose pose = RandomPose(rng);
      ViewCap cap = RandomCap(rng);
      const Eigen::Vector3d dir_s = pose.q_world_sensor.conjugate() * cap.dir;
      const double cos_cap = std::cos(cap.half_angle_rad);
      // The deepest pixel inside the cap; Reaches must say yes for any bound up to it.
      // Rows whose centres can lie within the cap (a row's pixels share their elevation).
      const double psi_c = std::asin(std::clamp(dir_s.z(), -1.0, 1.0));
      const double dpsi = M_PI / size.height_px;
      const int j0 = std::max(0, int((M_PI / 2 - psi_c - cap.half_angle_rad) / dpsi) - 1);
      const int j1 =
          std::min(size.height_px, int((M_PI / 2 - psi_c + cap.half_angle_rad) / dpsi) + 2);
      float deepest = -1.0f;
      for (int j = j0; j < j1; ++j) {
        for (int i = 0; i < size.width_px; ++i) {
          if (PixelDirection(i, j, size).dot(dir_s) >= cos_cap) {
            deepest = std::max(deepest, depth_m[size_t(j) * size.width_px + i]);
          }
        }
      }
      if (deepest < 5.0f) continue;  // no deep pixel (or no pixel centre) in the cap
      ++checked;
      EXPECT_TRUE(Reaches(reach, pose, cap, deepest))
          << size.width_px << "x" << size.height_px << " cap " << cap.half_angle_rad;
      reaching += Reaches(reach, pose, cap, 10.5) ? 1 : 0;  // deeper than any pixel
    }
  }
  EXPECT_GT(checked, 100);
  EXPECT_EQ(reaching, 0) << "a bound deeper than every pixel reaches nothing";
}

TEST(CellCoverage, CoversEveryPixelOfTheCapsAndOnlyThemWhenWhole) {
  std::mt19937 rng(11);
  for (double pitch : {0.0123, 0.0031, 0.0047}) {
    const geometry::EquirectSize size = ingest::DepthPanoramaSize(pitch);
    const geometry::EquirectSize cells = {size.width_px / kReachBlockPx,
                                          size.height_px / kReachBlockPx};
    for (int trial = 0; trial < 20; ++trial) {
      const geometry::Pose pose = RandomPose(rng);
      std::vector<ViewCap> caps = {RandomCap(rng), RandomCap(rng)};
      const std::vector<uint8_t> coverage = CellCoverage(cells, pose, caps);
      int inside = 0;
      for (int j = 0; j < size.height_px; ++j) {
        for (int i = 0; i < size.width_px; ++i) {
          const Eigen::Vector3d d = PixelDirection(i, j, size);
          bool in_cap = false;
          for (const ViewCap& cap : caps) {
            const Eigen::Vector3d dir_s = pose.q_world_sensor.conjugate() * cap.dir;
            in_cap = in_cap || d.dot(dir_s) >= std::cos(cap.half_angle_rad);
          }
          const uint8_t c =
              coverage[size_t(j / kReachBlockPx) * cells.width_px + i / kReachBlockPx];
          if (in_cap) {
            ++inside;
            ASSERT_GE(c, 1) << "pixel " << i << "," << j << " of " << size.width_px;
          } else {
            ASSERT_NE(c, 2) << "pixel " << i << "," << j << " of " << size.width_px;
          }
        }
      }
      EXPECT_GT(inside, 0);
    }
  }
}

// CapCells searches a cap clear of the poles over the columns of its azimuth span only: at the
// seam (φ = ±π), beside a pole and across one, it still visits every cell whose centre lies
// within the cap's radius plus a cell's half-diagonal, and no other.
TEST(CapCells, VisitsTheCellsOfCapsAtTheSeamAndThePoles) {
  const geometry::EquirectSize cells = {128, 64};
  const double half_diag = 0.5 * std::hypot(2.0 * M_PI / cells.width_px, M_PI / cells.height_px);
  geometry::Pose pose;
  pose.q_world_sensor =
      Eigen::Quaterniond(Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 2, 3).normalized()));
  const CapCells grid(cells, pose);
  int caps = 0;
  for (double psi : {0.0, 0.6, -1.2, 1.45, -1.5, 1.5707}) {
    for (double phi : {M_PI - 1e-4, -M_PI + 0.01, 0.3}) {
      for (double half : {0.001, 0.03, 0.2, 0.9}) {
        ViewCap cap;
        const Eigen::Vector3d d_s(std::cos(psi) * std::cos(phi), std::cos(psi) * std::sin(phi),
                                  std::sin(psi));
        cap.dir = pose.q_world_sensor * d_s;
        cap.half_angle_rad = half;
        std::vector<uint8_t> seen(size_t(cells.width_px) * cells.height_px, 0);
        grid.ForEach(cap, [&](size_t c, bool) {
          ++seen[c];
          return true;
        });
        for (int j = 0; j < cells.height_px; ++j) {
          for (int i = 0; i < cells.width_px; ++i) {
            const double angle =
                std::acos(std::clamp(PixelDirection(i, j, cells).dot(d_s), -1.0, 1.0));
            const bool in = angle <= half + half_diag - 1e-9;
            const bool out = angle > half + half_diag + 1e-9;
            const uint8_t n = seen[size_t(j) * cells.width_px + i];
            const std::string where = "cell " + std::to_string(i) + "," + std::to_string(j) +
                                      " psi " + std::to_string(psi) + " phi " + std::to_string(phi);
            if (in) ASSERT_EQ(n, 1) << where;
            if (out) ASSERT_EQ(n, 0) << where;
          }
        }
        ++caps;
      }
    }
  }
  EXPECT_EQ(caps, 72);
}

// CapPixelSpan (the rows and columns CapCells and the render's block skip search): every pixel
// whose centre lies within the radius, and each of its 8 neighbours (wrapped across the seam),
// lies in the span, at the seam, beside and across a pole, for sizes even and odd.
TEST(CapPixelSpan, HoldsThePixelsOfTheCapAndOneMore) {
  int spans = 0, narrowed = 0;
  for (const geometry::EquirectSize size : {geometry::EquirectSize{128, 64},
                                            geometry::EquirectSize{1025, 511}}) {
    const int W = size.width_px, H = size.height_px;
    for (double psi : {0.0, 0.6, -1.2, 1.5, -1.5707, 1.5707}) {
      for (double phi : {M_PI - 1e-4, -M_PI + 0.01, 0.3}) {
        for (double radius : {1e-4, 0.003, 0.05, 0.4, 1.2}) {
          const Eigen::Vector3d d(std::cos(psi) * std::cos(phi), std::cos(psi) * std::sin(phi),
                                  std::sin(psi));
          const PixelSpan span = CapPixelSpan(d, radius, size);
          ASSERT_GE(span.col_first, 0);
          ASSERT_LT(span.col_first, W);
          ASSERT_LE(span.col_count, W);
          narrowed += span.col_count < W;
          auto in_span = [&](int i, int j) {
            if (j < 0 || j >= H) return true;  // no such row
            const int from_first = ((i - span.col_first) % W + W) % W;
            return j >= span.row_first && j <= span.row_last && from_first < span.col_count;
          };
          for (int j = 0; j < H; ++j) {
            for (int i = 0; i < W; ++i) {
              if (PixelDirection(i, j, size).dot(d) < std::cos(radius)) continue;
              for (int dj = -1; dj <= 1; ++dj) {
                for (int di = -1; di <= 1; ++di) {
                  ASSERT_TRUE(in_span(i + di, j + dj))
                      << "pixel " << i + di << "," << j + dj << " of " << W << "x" << H
                      << ", psi " << psi << " phi " << phi << " radius " << radius;
                }
              }
            }
          }
          ++spans;
        }
      }
    }
  }
  EXPECT_EQ(spans, 180);
  EXPECT_GT(narrowed, 60) << "caps clear of the poles search their columns only";
}

}  // namespace
}  // namespace vasl::tiles

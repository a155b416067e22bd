/// @file corridor_lattice.h
/// @brief A GoogleTest fixture: the corridor site and the lattice its stations' LiDARs make
///        (720 × 360 returns each, h = 5 cm), built once per test suite. Header-only: the
///        scenes library does not link the ingest library whose voxelisation builds it.
#pragma once

#include <utility>

#include <gtest/gtest.h>

#include "lattice/ingest/voxelise.h"
#include "lattice/records/records.h"
#include "tests/scenes/corridor_site.h"

namespace vasl::scenes {

class CorridorLatticeTest : public ::testing::Test {
 public:
  static constexpr double kVosselM = 0.05;

 protected:
  static void SetUpTestSuite() {
    site_ = new CorridorSite(CorridorSite::Default());
    LidarSettings settings;
    settings.azimuth_steps = 720;
    settings.elevation_steps = 360;
    auto g = ingest::BuildGeometry(StationLidars(*site_, settings), kVosselM);
    ASSERT_TRUE(g.ok()) << g.status();
    geometry_ = new records::VosselGeometry(std::move(*g));
  }
  static void TearDownTestSuite() {
    delete site_;
    delete geometry_;
    site_ = nullptr;
    geometry_ = nullptr;
  }

  static inline CorridorSite* site_ = nullptr;
  static inline records::VosselGeometry* geometry_ = nullptr;
};

}  // namespace vasl::scenes

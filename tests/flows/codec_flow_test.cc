// Claims of codec artefacts at ingest (VASL-MODEL §9, §6, §7): a panorama at a novel view of
// the synthetic room, sent as a quality-15 JPEG with 4:2:0 chroma beside the stations' clean
// panoramas. Its records take conf[codec] from the codec map (below 1 on most of them: at this
// quality the codec moves most pixels by more than a tenth); a profile that weighs the codec
// (κ_codec = 2) fuses the vossels it lowered closer to their albedo than one that ignores it
// (κ_codec = 0), from the records alone: κ = 1 lowers the error, κ = 2 lowers it more and by
// at least 5% in all (the four stations' clean panoramas already hold most of the weight).
#include <cstdio>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "tests/flows/room_artefacts.h"
#include "tests/ingest/encode_srgb8.h"

namespace vasl {
namespace {
namespace fs = std::filesystem;

TEST(CodecFlowTest, CodecLowersTheRecordsConfidenceAndWeighingItMendsTheColour) {
  const fs::path dir =
      fs::temp_directory_path() / ("vasl-codec-flow-test-" + std::to_string(::getpid()));
  const scenes::SyntheticRoom room = scenes::SyntheticRoom::Default();
  std::unique_ptr<Engine> engine = RoomWithStations(dir, room);
  ASSERT_TRUE(engine != nullptr);
  const geometry::Pose pose = room.NovelViews()[0];
  const scenes::Panorama pano = scenes::RenderPanorama(room, pose, 1024, 512, 2);
  auto scan = scenes::PanoramaScan("jpeg-15", pose, pano);
  ASSERT_TRUE(scan.ok()) << scan.status();
  geometry::LinearImage linear;
  linear.width_px = pano.width_px;
  linear.height_px = pano.height_px;
  linear.channels = 3;
  linear.pixels = pano.rgb;
  scan->panoramas.at(0).encoded_image = EncodeSrgb8(linear, "jpg", 15);
  const AfterIngest after = IngestAndLoad(*engine, dir, *scan);
  ASSERT_TRUE(after.snap != nullptr);
  const int32_t camera = after.camera;
  const records::RecordSet& rec = after.snap->records;
  const records::VosselGeometry& g = after.snap->geometry;
  size_t records = 0, lowered = 0, others_lowered = 0;
  std::vector<uint8_t> affected(g.size(), 0);
  for (size_t i = 0; i < rec.size(); ++i) {
    const float conf = rec.conf[i * records::kConfidenceCount + records::kConfCodec];
    if (rec.scan[i] != camera) {
      others_lowered += conf < 1.0f;
      continue;
    }
    ++records;
    if (conf < 1.0f) {
      ++lowered;
      affected[size_t(rec.vossel[i])] = 1;
    }
  }
  std::printf("quality-15 camera: %zu records, %zu with conf[codec] < 1; records of the clean "
              "(PNG) panoramas and LiDAR below 1: %zu\n", records, lowered, others_lowered);
  EXPECT_GT(records, 10000u);
  EXPECT_GE(lowered, records / 2);
  EXPECT_EQ(others_lowered, 0u);
  auto error_with = [&](double kappa) {
    return FusedError(rec, g, affected, room, pose, ProfileWith(records::kConfCodec, kappa));
  };
  const auto [ignored, n0] = error_with(0.0);
  const auto [one, n1] = error_with(1.0);
  const auto [weighed, n2] = error_with(2.0);
  std::printf("fused colour of %zu vossels the codec map lowered, mean |error| against the "
              "albedo: %.4f ignoring the codec (kappa 0), %.4f with kappa 1, %.4f with kappa 2\n",
              n0, ignored, one, weighed);
  EXPECT_GT(n0, 1000u);
  EXPECT_LT(one, ignored);
  EXPECT_LT(weighed, one);
  EXPECT_LT(weighed, 0.95 * ignored);
  engine.reset();
  fs::remove_all(dir);
}

}  // namespace
}  // namespace vasl

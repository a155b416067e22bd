// Visual references (issue "Real captures in"; E57 visualReferenceRepresentation): a photo sent
// with a scan for people to look at is kept as a blob with the scan's provenance and comes back
// byte for byte, with its pose in world coordinates; it is no source and changes no record; it
// lives as long as a kept version has its scan (retention keeps it through later commits and
// collects it once the scan's last version goes); a scan of references alone is refused.
#include <filesystem>

#include <gtest/gtest.h>

#include "lattice/engine.h"
#include "tests/scenes/synthetic_scene.h"

namespace vasl {
namespace {
namespace fs = std::filesystem;

constexpr double kVosselM = 0.05;
constexpr int kPanoW = 256;

// A 4:3 photo of the room (any image: a reference has no projection).
std::string ReferencePhoto(const scenes::SyntheticRoom& room) {
  geometry::PinholeIntrinsics k = scenes::SurveyPhotoIntrinsics();
  k.width_px = 160, k.height_px = 120, k.fx_px /= 4, k.fy_px /= 4, k.cx_px /= 4, k.cy_px /= 4;
  const geometry::Pose pose = scenes::LookAt(room.Stations()[0].o_world, room.OccluderBounds().max_m);
  absl::StatusOr<std::string> png = scenes::EncodePng(scenes::RenderPinhole(room, pose, k, 1));
  EXPECT_TRUE(png.ok()) << png.status();
  return *png;
}

TEST(VisualReferenceTest, KeptWithTheScanReturnedAsSentAndCollectedWithIt) {
  const fs::path dir = fs::temp_directory_path() / ("vasl-visref-" + std::to_string(::getpid()));
  fs::remove_all(dir);
  auto engine = Engine::Open(dir);
  ASSERT_TRUE(engine.ok()) << engine.status();
  const scenes::SyntheticRoom room = scenes::SyntheticRoom::Default();
  store::ProjectSettings settings;
  settings.vossel_size_m = kVosselM;
  settings.keep_versions = 0;  // retention keeps HEAD (and pins) only
  settings.origin_m = Eigen::Vector3d(1000.0, 2000.0, 0.0);
  for (const char* project : {"with", "without"}) {
    ASSERT_TRUE((*engine)->CreateProject(project, settings).ok());
  }
  auto scan = scenes::MakeScanInput(room, 0, scenes::LidarSettings::Small(1), kPanoW);
  ASSERT_TRUE(scan.ok()) << scan.status();
  for (ingest::PanoramaData& pano : scan->panoramas) pano.pose.o_world += *settings.origin_m;
  scan->pose.o_world += *settings.origin_m;
  ASSERT_TRUE((*engine)->IngestScan("without", *scan).ok());

  ingest::PanoramaData ref;
  ref.name = "site photo";
  ref.pose = scan->pose;
  ref.encoded_image = ReferencePhoto(room);
  ref.visual_reference = true;
  scan->panoramas.insert(scan->panoramas.begin(), ref);  // before the camera: order is free
  auto with = (*engine)->IngestScan("with", *scan);
  ASSERT_TRUE(with.ok()) << with.status();
  auto without_info = (*engine)->GetProject("without");
  ASSERT_TRUE(without_info.ok());
  EXPECT_EQ(with->record_count, without_info->record_count);  // no source, no record
  EXPECT_EQ(with->vossel_count, without_info->vossel_count);
  ASSERT_EQ(with->calibration.size(), 1u);  // the camera was checked; the reference was not
  EXPECT_EQ(with->calibration[0].first, "cam0");

  auto scans = (*engine)->ListScans("with");
  ASSERT_TRUE(scans.ok()) << scans.status();
  ASSERT_EQ(scans->size(), 1u);
  const store::ScanInfo& listed = (*scans)[0];
  ASSERT_EQ(listed.visual_references.size(), 1u);
  const store::VisualReferenceInfo& kept = listed.visual_references[0];
  EXPECT_EQ(kept.name, "site photo");
  EXPECT_EQ(kept.width_px, 160);
  EXPECT_EQ(kept.height_px, 120);
  EXPECT_EQ(kept.size_bytes, int64_t(ref.encoded_image.size()));
  EXPECT_LT((kept.pose.o_world - ref.pose.o_world).norm(), 1e-9);  // world coordinates
  for (const store::SourceInfo& src : listed.sources) EXPECT_NE(src.name, "site photo");

  auto back = (*engine)->GetVisualReference("with", scan->scan_name, "site photo");
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->second, ref.encoded_image);
  auto missing = (*engine)->GetVisualReference("with", scan->scan_name, "nope");
  EXPECT_EQ(missing.status().code(), absl::StatusCode::kNotFound);
  EXPECT_NE(missing.status().message().find("site photo"), std::string::npos);

  // Retention keeps the blob while a kept version has the scan, and collects it after.
  const fs::path blob = dir / "with" / "blobs" / kept.blob_sha256;
  auto second = scenes::MakeScanInput(room, 1, scenes::LidarSettings::Small(2), kPanoW);
  ASSERT_TRUE(second.ok());
  second->pose.o_world += *settings.origin_m;
  for (ingest::PanoramaData& pano : second->panoramas) pano.pose.o_world += *settings.origin_m;
  ASSERT_TRUE((*engine)->IngestScan("with", *second).ok());
  EXPECT_TRUE(fs::exists(blob)) << blob;
  ASSERT_TRUE((*engine)->DeleteScan("with", scan->scan_name).ok());
  EXPECT_FALSE(fs::exists(blob)) << blob;

  // References alone colour nothing: refused, nothing stored.
  ingest::ScanInput alone;
  alone.scan_name = "photos only";
  alone.pose = scan->pose;
  alone.panoramas.push_back(ref);
  auto refused = (*engine)->IngestScan("with", alone);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(refused.status().message().find("visual references alone"), std::string::npos)
      << refused.status();
  engine->reset();
  fs::remove_all(dir);
}

}  // namespace
}  // namespace vasl

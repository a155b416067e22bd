// Stopping long work (ARCHITECTURE.md "Errors and limits"): a change, a reweight or a render
// whose caller no longer wants it (ingest::ProgressFn, RenderRequest::interrupt answer with a
// status) stops where it is, with that status, and leaves the project as it was; so does an
// ingest whose panorama fails only when its pixels are decoded, one panorama at a time.
#include <fstream>
#include <iterator>
#include <map>
#include <string>

#include <gtest/gtest.h>

#include "lattice/engine.h"
#include "tests/scenes/synthetic_scene.h"

namespace vasl {
namespace {

namespace fs = std::filesystem;

// Every file of a project but its catalog (SQLite may checkpoint its WAL at any read), by
// relative path, with its bytes: what a stopped change must leave byte-identical.
std::map<std::string, std::string> ProjectFiles(const fs::path& dir) {
  std::map<std::string, std::string> out;
  for (const auto& entry : fs::recursive_directory_iterator(dir)) {
    if (!entry.is_regular_file()) continue;
    const std::string rel = fs::relative(entry.path(), dir).string();
    if (rel.rfind("catalog.sqlite", 0) == 0) continue;
    std::ifstream in(entry.path(), std::ios::binary);
    out[rel] = std::string(std::istreambuf_iterator<char>(in), {});
  }
  return out;
}

class CancelTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() / ("vasl-cancel-test-" + std::to_string(::getpid()));
    fs::remove_all(dir_);
    auto engine = Engine::Open(dir_);
    ASSERT_TRUE(engine.ok()) << engine.status();
    engine_ = std::move(*engine);
    store::ProjectSettings settings;
    settings.vossel_size_m = 0.05;
    ASSERT_TRUE(engine_->CreateProject("site", settings).ok());
    scenes::LidarSettings lidar;
    lidar.azimuth_steps = 360;
    lidar.elevation_steps = 180;
    for (size_t i = 0; i < 2; ++i) {
      lidar.seed = i + 1;
      auto scan = scenes::MakeScanInput(room_, i, lidar, 256);
      ASSERT_TRUE(scan.ok()) << scan.status();
      scans_.push_back(std::move(*scan));
    }
    auto first = engine_->IngestScan("site", scans_[0]);
    ASSERT_TRUE(first.ok()) << first.status();
  }
  void TearDown() override {
    engine_.reset();
    fs::remove_all(dir_);
  }

  // The project's state as a user sees it: HEAD, scans, records, and its files' bytes.
  void ExpectUnchanged(const ProjectInfo& before, const std::map<std::string, std::string>& files,
                       const std::string& what) {
    auto after = engine_->GetProject("site");
    ASSERT_TRUE(after.ok()) << after.status();
    EXPECT_EQ(after->head_version, before.head_version) << what;
    EXPECT_EQ(after->scan_count, before.scan_count) << what;
    EXPECT_EQ(after->record_count, before.record_count) << what;
    const auto now = ProjectFiles(dir_ / "site");
    EXPECT_EQ(now.size(), files.size()) << what << ": a file was left behind or removed";
    EXPECT_TRUE(now == files) << what << ": the project's files changed";
  }

  fs::path dir_;
  std::unique_ptr<Engine> engine_;
  scenes::SyntheticRoom room_ = scenes::SyntheticRoom::Default();
  std::vector<ScanInput> scans_;
};

// Claim: an ingest stopped as any of its stages starts (validate, store blobs, voxelise,
// normals, find changes, revisits, records, fuse, commit) answers with the caller's status,
// commits nothing, records no operation under its request id and leaves every file of the
// project byte-identical (the blobs it stored are collected); the same ingest then runs whole.
TEST_F(CancelTest, AnIngestStoppedAtAnyStageLeavesTheProjectAsItWas) {
  auto before = engine_->GetProject("site");
  ASSERT_TRUE(before.ok());
  const auto files = ProjectFiles(dir_ / "site");
  ScanInput scan = scans_[1];
  scan.request_id = "cancel-ingest-1";
  int stopped_at = 0;
  for (int stop = 0;; ++stop) {
    int seen = 0;
    std::string stage;
    auto result = engine_->IngestScan("site", scan, [&](const Progress& p) {
      if (seen++ < stop) return absl::OkStatus();
      stage = p.stage;
      return absl::CancelledError("the client cancelled the call");
    });
    if (result.ok()) {
      EXPECT_EQ(result->version, before->head_version + 1);
      EXPECT_FALSE(result->replayed);
      break;
    }
    ++stopped_at;
    EXPECT_EQ(result.status().code(), absl::StatusCode::kCancelled) << result.status();
    ExpectUnchanged(*before, files, "ingest stopped at stage '" + stage + "'");
    auto op = engine_->FindOperation("site", {scan.request_id, "", ""});
    ASSERT_TRUE(op.ok()) << op.status();
    EXPECT_FALSE(op->has_value()) << "a stopped ingest recorded its request id";
    std::printf("ingest stopped at stage %d '%s': %s\n", stop, stage.c_str(),
                std::string(result.status().message()).c_str());
  }
  EXPECT_GE(stopped_at, 8) << "the ingest reports fewer stages than it has";
  auto scans = engine_->ListScans("site");
  ASSERT_TRUE(scans.ok());
  EXPECT_EQ(scans->size(), 2u);
}

// Claim: panoramas are decoded one at a time as their cameras are sampled, after validation
// read their headers; one whose header reads but whose pixels do not decode fails the ingest
// with INVALID_ARGUMENT naming the scan and the panorama, and the project stays as it was.
TEST_F(CancelTest, APanoramaWhosePixelsDoNotDecodeLeavesTheProjectAsItWas) {
  auto before = engine_->GetProject("site");
  ASSERT_TRUE(before.ok());
  const auto files = ProjectFiles(dir_ / "site");
  ScanInput scan = scans_[1];
  ASSERT_FALSE(scan.panoramas.empty());
  PanoramaData second = scan.panoramas[0];
  second.name = "cut";
  second.encoded_image.resize(second.encoded_image.size() / 2);  // header whole, pixels cut
  scan.panoramas.push_back(second);
  auto result = engine_->IngestScan("site", scan);
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument) << result.status();
  const std::string message(result.status().message());
  EXPECT_NE(message.find("scan '" + scan.scan_name + "', panorama 'cut'"), std::string::npos)
      << message;
  std::printf("truncated panorama: %s\n", message.c_str());
  ExpectUnchanged(*before, files, "ingest with a truncated panorama");
}

// Claim: a reweight stopped after its first tile answers with the caller's status and leaves
// the project byte-identical (the fused tiles it wrote are collected); under a request id it
// then runs once, and a retry is answered from its commit.
TEST_F(CancelTest, AReweightStoppedMidwayLeavesTheProjectAsItWas) {
  fusion::WeightingProfile p;
  p.name = "far";
  p.proximity_m = 4.0;
  ASSERT_TRUE(engine_->CreateProfile("site", p).ok());
  auto before = engine_->GetProject("site");
  ASSERT_TRUE(before.ok());
  const auto files = ProjectFiles(dir_ / "site");
  auto stopped = engine_->Reweight("site", "far", 0, [](const Progress&) {
    return absl::DeadlineExceededError("the deadline passed");
  }, "reweight-far-1");
  EXPECT_EQ(stopped.status().code(), absl::StatusCode::kDeadlineExceeded) << stopped.status();
  ExpectUnchanged(*before, files, "reweight stopped after its first tile");

  auto done = engine_->Reweight("site", "far", 0, {}, "reweight-far-1");
  ASSERT_TRUE(done.ok()) << done.status();
  EXPECT_FALSE(done->replayed);
  EXPECT_EQ(done->version, before->head_version + 1);
  auto again = engine_->Reweight("site", "far", 0, {}, "reweight-far-1");
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_TRUE(again->replayed);
  EXPECT_EQ(again->version, done->version);
  EXPECT_EQ(engine_->GetProject("site")->head_version, done->version) << "no second version";
  auto other = engine_->Reweight("site", "default", 0, {}, "reweight-far-1");
  EXPECT_EQ(other.status().code(), absl::StatusCode::kFailedPrecondition) << other.status();
}

// Claim: a render whose caller stops wanting it ends with the caller's status, after marching
// only part of its rows; one whose caller keeps waiting renders whole.
TEST_F(CancelTest, ARenderStopsWhenItsCallerGoesAway) {
  RenderRequest request;
  request.pose = room_.Stations()[0];
  request.width_px = 512;
  request.height_px = 256;
  std::atomic<int> asked{0};
  request.interrupt = [&asked]() {
    return ++asked > 16 ? absl::CancelledError("the client cancelled the call") : absl::OkStatus();
  };
  auto stopped = engine_->Render("site", request);
  EXPECT_EQ(stopped.status().code(), absl::StatusCode::kCancelled) << stopped.status();
  EXPECT_LT(asked.load(), 256 + 1) << "every row was marched";
  request.interrupt = [] { return absl::OkStatus(); };
  auto whole = engine_->Render("site", request);
  ASSERT_TRUE(whole.ok()) << whole.status();
  EXPECT_GT(whole->hit_pixels, 512 * 256 / 2);
}

}  // namespace
}  // namespace vasl

// The decoded images revisits keep between ingests (flows.h SourceImageCache, LoadedCamera):
// a camera read through the cache is the camera its blob decodes to (an 8-bit one read back
// from its codes, a float one with its channel shift corrected), with the artefact maps its
// records would find (§9), whether the cache held it or not; a camera kept so gives the
// records of one decoded afresh; and the cache holds no more
// than its budget, the least recently used going first. A LiDAR read through it is the stored
// one with its gap fill.
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <memory>
#include <optional>
#include <string>

#include <gtest/gtest.h>

#include "lattice/engine.h"
#include "lattice/flows/flows.h"
#include "lattice/geometry/linear_image.h"
#include "lattice/ingest/artefacts.h"
#include "lattice/ingest/sample.h"
#include "lattice/ingest/validate.h"
#include "lattice/ingest/voxelise.h"
#include "lattice/store/project_store.h"
#include "tests/scenes/synthetic_scene.h"

namespace vasl {
namespace {
namespace fs = std::filesystem;

std::shared_ptr<const geometry::LinearImage> Image(int w, int h, float v) {
  auto im = std::make_shared<geometry::LinearImage>();
  im->width_px = w;
  im->height_px = h;
  im->channels = 3;
  im->pixels.assign(size_t(w) * h * 3, v);
  return im;
}

TEST(SourceImageCache, KeepsTheMostRecentlyUsedWithinItsBudgetArtefactsIncluded) {
  const int64_t one = 100 * 100 * 3 * int64_t(sizeof(float));  // an image's bytes
  flows::SourceImageCache cache(3 * one);
  auto maps = std::make_shared<ingest::ArtefactMaps>();
  maps->saturation.conf = *Image(100, 100, 1.0f);  // counts as much as an image (3 channels)
  cache.Put("a", Image(100, 100, 0.1f), maps);     // 2 images' bytes
  cache.Put("b", Image(100, 100, 0.2f));
  std::shared_ptr<const ingest::ArtefactMaps> found;
  ASSERT_NE(cache.Find("a", &found), nullptr);  // a is now the most recent
  EXPECT_EQ(found, maps);
  cache.Put("c", Image(100, 100, 0.3f));  // over budget: b (least recent) goes
  EXPECT_EQ(cache.Find("b"), nullptr);
  ASSERT_NE(cache.Find("a"), nullptr);
  ASSERT_NE(cache.Find("c"), nullptr);
  cache.Put("d", Image(200, 200, 0.4f));  // larger than the budget: not kept, nothing evicted
  EXPECT_EQ(cache.Find("d"), nullptr);
  EXPECT_NE(cache.Find("a"), nullptr);
  flows::SourceImageCache none(0);
  none.Put("a", Image(1, 1, 0.5f));
  EXPECT_EQ(none.Find("a"), nullptr);
}

// GreedyDual-Size: an entry that cost more per byte to make outlives cheaper ones, however
// recently those were used (a revisit's cameras stay, its LiDARs reload); among entries of
// equal cost per byte the least recently used goes; and one left unused long enough goes too,
// as every eviction raises the worth a use gives.
TEST(SourceImageCache, KeepsWhatCostMostPerByteAndAgesWhatIsNotUsed) {
  const int64_t one = 100 * 100 * 3 * int64_t(sizeof(float));
  flows::SourceImageCache cache(3 * one);
  cache.Put("dear1", Image(100, 100, 0.1f), nullptr, 1.0);
  cache.Put("cheap", Image(100, 100, 0.2f), nullptr, 0.01);
  cache.Put("dear2", Image(100, 100, 0.3f), nullptr, 1.0);
  ASSERT_NE(cache.Find("cheap"), nullptr);  // the most recently used
  cache.Put("dear3", Image(100, 100, 0.4f), nullptr, 1.0);
  EXPECT_EQ(cache.Find("cheap"), nullptr);  // the least worth went, not the least recent
  EXPECT_NE(cache.Find("dear2"), nullptr);
  EXPECT_NE(cache.Find("dear3"), nullptr);
  EXPECT_NE(cache.Find("dear1"), nullptr);  // now the most recently used of equals
  cache.Put("dear4", Image(100, 100, 0.5f), nullptr, 1.0);
  EXPECT_EQ(cache.Find("dear2"), nullptr);  // equal cost per byte: the least recently used
  EXPECT_NE(cache.Find("dear1"), nullptr);
  // Cheap entries coming and going raise the worth a use gives, until the dear ones left
  // unused are worth less than a fresh cheap one: they go too.
  for (int i = 0; i < 400; ++i) {
    cache.Put("cheap" + std::to_string(i), Image(100, 100, 0.6f), nullptr, 0.01);
  }
  EXPECT_EQ(cache.Find("dear1"), nullptr);
  EXPECT_EQ(cache.Find("dear3"), nullptr);
  EXPECT_EQ(cache.Find("dear4"), nullptr);
  EXPECT_NE(cache.Find("cheap399"), nullptr);
}

// One scan of the synthetic room, with its range grid, ingested into a project; its store open.
class StoredRoom : public ::testing::Test {
 protected:
  void SetUp() override {
    root_ = fs::temp_directory_path() / ("vasl-image-cache-" + std::to_string(::getpid()));
    fs::remove_all(root_);
    auto engine = Engine::Open(root_);
    ASSERT_TRUE(engine.ok()) << engine.status();
    store::ProjectSettings settings;
    settings.vossel_size_m = 0.05;
    ASSERT_TRUE((*engine)->CreateProject("room", settings).ok());
    const scenes::SyntheticRoom room = scenes::SyntheticRoom::Default();
    auto scan = scenes::MakeScanInput(room, 0, scenes::LidarSettings::Small(1), 512, 2);
    ASSERT_TRUE(scan.ok()) << scan.status();
    scenes::SetRangeGrid(scenes::LidarSettings::Small(1), &scan->lidar);  // a gap fill to keep
    ASSERT_TRUE((*engine)->IngestScan("room", *scan).ok());
    auto st = store::ProjectStore::Open(root_ / "room");
    ASSERT_TRUE(st.ok()) << st.status();
    store_ = std::move(*st);
    scans_ = *store_->ListScans();
  }
  void TearDown() override {
    store_.reset();
    fs::remove_all(root_);
  }
  const store::SourceInfo* Source(records::Modality modality) const {
    for (const store::SourceInfo& s : scans_.at(0).sources) {
      if (s.modality == modality) return &s;
    }
    return nullptr;
  }

  fs::path root_;
  std::unique_ptr<store::ProjectStore> store_;
  std::vector<store::ScanInfo> scans_;
};

TEST_F(StoredRoom, LoadedCameraIsTheDecodedCameraWithItsArtefactsFromTheCacheOrNot) {
  const std::unique_ptr<store::ProjectStore>& st = store_;
  const std::vector<store::ScanInfo>& scans = scans_;
  const store::SourceInfo* camera = Source(records::Modality::kRgb);
  ASSERT_NE(camera, nullptr);
  const int64_t max_pixels = 1 << 24;

  // Without a cache: decoded on demand, as ever.
  ingest::CameraSource lazy = flows::StoredCamera(*st, *camera, scans[0].batch, max_pixels);
  absl::StatusOr<ingest::LinearImage> decoded = lazy.load();
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  const ingest::ArtefactMaps expected = ingest::DetectArtefacts(*decoded, /*wrap=*/true);
  auto uncached = flows::LoadedCamera(*st, *camera, scans[0].batch, max_pixels, nullptr);
  ASSERT_TRUE(uncached.ok()) << uncached.status();
  EXPECT_TRUE(uncached->image.pixels.empty());
  EXPECT_EQ(uncached->artefacts, nullptr);

  // Through a cache: a miss decodes and keeps, a hit gives the same maps; both the decode's.
  // An 8-bit panorama is kept as its codes, a quarter of its bytes: a budget too small for the
  // decoded image but large enough for its codes and maps keeps it, and the hit needs no blob.
  ASSERT_TRUE(geometry::PackSrgb8(*decoded).has_value()) << "the synthetic PNG is 8-bit";
  int64_t maps_bytes = 0;
  for (const ingest::LinearImage* map : {&expected.saturation.conf, &expected.smear.conf,
                                         &expected.flare.conf, &expected.codec.conf}) {
    maps_bytes += int64_t(map->ByteSize());
  }
  const int64_t budget = int64_t(decoded->ByteSize() / 4) + maps_bytes + 1024;
  ASSERT_LT(budget, int64_t(decoded->ByteSize()) + maps_bytes);
  flows::SourceImageCache cache(budget);
  auto first = flows::LoadedCamera(*st, *camera, scans[0].batch, max_pixels, &cache);
  ASSERT_TRUE(fs::remove(root_ / "room" / "blobs" / camera->blob_sha256))
      << "the blob a miss would decode again";
  auto second = flows::LoadedCamera(*st, *camera, scans[0].batch, max_pixels, &cache);
  ASSERT_TRUE(first.ok()) << first.status();
  ASSERT_TRUE(second.ok()) << second.status();
  EXPECT_EQ(first->artefacts, second->artefacts);  // the kept maps, shared
  // Both read the codes: unpacked when their records are sampled (with the blob gone), the
  // image as decoded, its channel shift left to the rows the records read (CameraRecords).
  for (const ingest::CameraSource* cam : {&*first, &*second}) {
    EXPECT_TRUE(cam->image.pixels.empty());
    EXPECT_EQ(cam->kept_image, nullptr);
    ASSERT_TRUE(cam->load != nullptr);
    absl::StatusOr<ingest::LinearImage> unpacked = cam->load();
    ASSERT_TRUE(unpacked.ok()) << unpacked.status();
    EXPECT_EQ(unpacked->width_px, decoded->width_px);
    EXPECT_EQ(unpacked->pixels, decoded->pixels);
    ASSERT_NE(cam->artefacts, nullptr);
    EXPECT_EQ(cam->artefacts->fringing.found, expected.fringing.found);
    EXPECT_EQ(cam->artefacts->saturation.conf.pixels, expected.saturation.conf.pixels);
    EXPECT_EQ(cam->artefacts->flare.conf.pixels, expected.flare.conf.pixels);
    EXPECT_EQ(cam->artefacts->smear.conf.pixels, expected.smear.conf.pixels);
    EXPECT_EQ(cam->artefacts->codec.conf.pixels, expected.codec.conf.pixels);
  }
}

// A LiDAR read through the cache has the points LoadLidar reads and the gap fill GapFill
// computes, whether the cache held it or not; a hit shares the kept one; a cache too small for
// it keeps nothing.
TEST_F(StoredRoom, LoadedLidarIsTheStoredLidarWithItsGapFillFromTheCacheOrNot) {
  const store::SourceInfo* src = Source(records::Modality::kLidar);
  ASSERT_NE(src, nullptr);
  const int32_t batch = scans_[0].batch;
  auto fresh = flows::LoadLidar(*store_, *src, batch);
  ASSERT_TRUE(fresh.ok()) << fresh.status();
  ASSERT_TRUE(fresh->HasGrid()) << "the synthetic scan has a range grid";
  const std::shared_ptr<const ingest::GapFillPoints> fill = ingest::GapFill(*fresh, 0.05);
  ASSERT_GT(fill->size(), 0u);

  flows::SourceImageCache cache(int64_t(256) << 20), tiny(1024);
  for (flows::SourceImageCache* images : {static_cast<flows::SourceImageCache*>(nullptr), &tiny,
                                          &cache}) {
    auto first = flows::LoadedLidar(*store_, *src, batch, images);
    auto second = flows::LoadedLidar(*store_, *src, batch, images);
    ASSERT_TRUE(first.ok()) << first.status();
    ASSERT_TRUE(second.ok()) << second.status();
    EXPECT_EQ(*first == *second, images == &cache) << "only a cache it fits in shares it";
    for (const auto* l : {&**first, &**second}) {
      EXPECT_EQ(l->id, src->id);
      EXPECT_EQ(l->batch, batch);
      EXPECT_EQ(l->xyz_sensor_m, fresh->xyz_sensor_m);
      EXPECT_EQ(l->intensity, fresh->intensity);
      EXPECT_EQ(l->grid_cell, fresh->grid_cell);
      ASSERT_NE(l->gap_fill, nullptr);
      EXPECT_EQ(l->gap_fill->x, fill->x);
      EXPECT_EQ(l->gap_fill->corner, fill->corner);
      EXPECT_EQ(l->gap_fill->weight, fill->weight);
    }
  }
}

// Claim (§9): a camera whose kept image had its channel shift corrected once, whole, gives
// exactly the records of the same camera decoded afresh, which corrects only the rows its
// samples read in a copy, and of the camera kept as its 8-bit codes, which unpacks them and
// corrects those rows in place. A shift is planted (red and blue 0.6 and 0.4 px apart from green) so
// that the correction applies.
TEST(LoadedCamera, AKeptCorrectedImageGivesTheRecordsOfAFreshDecode) {
  const scenes::SyntheticRoom room = scenes::SyntheticRoom::Default();
  auto scan = scenes::MakeScanInput(room, 0, scenes::LidarSettings::Small(1), 512, 2);
  ASSERT_TRUE(scan.ok()) << scan.status();
  ingest::LidarSource lidar;
  lidar.id = 1;
  lidar.pose = scan->pose;
  lidar.xyz_sensor_m = scan->lidar.xyz_sensor_m;
  lidar.intensity = scan->lidar.intensity;
  auto g = ingest::BuildGeometry({lidar}, 0.05);
  ASSERT_TRUE(g.ok()) << g.status();
  auto image = ingest::DecodePanorama(*scan, 0, int64_t(1) << 24);
  ASSERT_TRUE(image.ok()) << image.status();
  auto artefacts = std::make_shared<ingest::ArtefactMaps>(ingest::DetectArtefacts(*image, true));
  ingest::ChannelShift& shift = artefacts->fringing;
  shift.found = true;
  shift.wrap = true;
  shift.width_px = image->width_px;
  shift.height_px = image->height_px;
  shift.dx[0] = 0.6;
  shift.dy[0] = 0.2;
  shift.dx[2] = -0.4;
  shift.dy[2] = 0.1;
  shift.tiles_x = shift.tiles_y = 1;
  shift.tile_dx = {0.6f, -0.4f};
  shift.tile_dy = {0.2f, 0.1f};
  shift.max_offset_px = 0.64;

  ingest::CameraSource fresh;
  fresh.id = 2;
  fresh.pose = scan->panoramas[0].pose;
  fresh.image = *image;
  fresh.artefacts = artefacts;
  ingest::CameraSource kept = fresh;
  kept.image = ingest::LinearImage{};
  auto whole = std::make_shared<ingest::LinearImage>(*image);
  ASSERT_GT(ingest::CorrectChannelShift(*whole, shift), 0) << "the planted shift must apply";
  kept.kept_image = whole;

  // Kept as its codes (LoadedCamera's 8-bit cameras): unpacked on load, corrected by the records.
  std::optional<geometry::Srgb8Image> packed = geometry::PackSrgb8(*image);
  ASSERT_TRUE(packed.has_value()) << "the synthetic PNG is 8-bit";
  auto codes = std::make_shared<const geometry::Srgb8Image>(std::move(*packed));
  ingest::CameraSource coded = kept;
  coded.kept_image.reset();
  coded.load = [codes]() -> absl::StatusOr<ingest::LinearImage> {
    return geometry::UnpackSrgb8(*codes);
  };
  // And read by rows (LoadedCamera's, for revisits): the rows the samples read, with those
  // their correction reads, unpacked alone.
  ingest::CameraSource banded = coded;
  banded.image = codes->header;
  int band_rows = -1;
  banded.load_rows = [codes, &band_rows](int row_begin, int row_end) {
    geometry::LinearImage band = geometry::UnpackSrgb8Rows(*codes, row_begin, row_end);
    band_rows = band.HeldRows();
    return absl::StatusOr<ingest::LinearImage>(std::move(band));
  };

  auto same = [](const records::RecordSet& a, const records::RecordSet& b) {
    EXPECT_EQ(a.vossel, b.vossel);
    EXPECT_EQ(a.value, b.value);
    EXPECT_EQ(a.vis, b.vis);
    EXPECT_EQ(a.conf, b.conf);
    EXPECT_EQ(a.flags, b.flags);
  };
  auto a = ingest::CameraRecords(*g, fresh);
  ASSERT_TRUE(a.ok()) << a.status();
  ASSERT_GT(a->records.size(), 1000u);
  a->records.SortByVossel();  // parallel sampling gives them in any order
  for (const ingest::CameraSource* other : {&kept, &coded, &banded}) {
    auto b = ingest::CameraRecords(*g, *other);
    ASSERT_TRUE(b.ok()) << b.status();
    b->records.SortByVossel();
    same(a->records, b->records);
  }
  EXPECT_EQ(fresh.image.pixels, image->pixels) << "the fresh camera's own image stays as decoded";

  // A revisit's few vossels (those 10° to 15° above the camera's horizon): the band holds a
  // few of the image's rows, and the records are those of the whole image.
  std::vector<uint8_t> only(g->size(), 0);
  for (size_t k = 0; k < g->size(); ++k) {
    const Eigen::Vector3d d = g->FrameCentroid(k).cast<double>() - fresh.pose.o_world;
    const double elevation_deg = std::asin(d.z() / d.norm()) * 180.0 / M_PI;
    only[k] = elevation_deg >= 10.0 && elevation_deg <= 15.0;
  }
  auto few = ingest::CameraRecords(*g, fresh, &only, nullptr);
  auto few_banded = ingest::CameraRecords(*g, banded, &only, nullptr);
  ASSERT_TRUE(few.ok()) << few.status();
  ASSERT_TRUE(few_banded.ok()) << few_banded.status();
  ASSERT_GT(few->records.size(), 50u);
  few->records.SortByVossel();
  few_banded->records.SortByVossel();
  same(few->records, few_banded->records);
  EXPECT_GT(band_rows, 0);
  EXPECT_LT(band_rows, image->height_px / 4) << "of " << image->height_px << " rows";
  std::printf("a revisit of %zu records unpacked %d of %d rows\n", few->records.size(),
              band_rows, image->height_px);
}

}  // namespace
}  // namespace vasl

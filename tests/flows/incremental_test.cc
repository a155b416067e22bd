// Claims of the incremental flows (lattice/flows/flows.h): ingesting scans one at a time, or
// deleting one, gives the same project, record by record, as recomputing it from the raw blobs
// (rebuild) or ingesting the remaining scans alone; a new object turns exactly the older
// records behind it to shadow.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <map>
#include <tuple>

#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>
#include <gtest/gtest.h>

#include "lattice/engine.h"
#include "lattice/render/encode.h"
#include "lattice/store/project_store.h"
#include "lattice/tiles/tiling.h"
#include "tests/scenes/corridor_site.h"
#include "tests/scenes/random_site.h"
#include "tests/scenes/synthetic_scene.h"

namespace vasl {
namespace {
namespace fs = std::filesystem;

constexpr double kVosselM = 0.05;
constexpr int kPanoW = 512;

fs::path TestRoot(const std::string& name) {
  const fs::path root = fs::temp_directory_path() /
                        ("vasl-incremental-" + name + "-" + std::to_string(::getpid()));
  fs::remove_all(root);
  return root;
}

/// (scan name, source name) of every source id of a project's HEAD, so that two projects whose
/// ids differ can be compared.
std::map<int32_t, std::string> SourceNames(const store::ProjectStore& st) {
  std::map<int32_t, std::string> out;
  const std::vector<store::ScanInfo> scans = *st.ListScans();
  for (const store::ScanInfo& scan : scans) {
    for (const store::SourceInfo& src : scan.sources) out[src.id] = scan.name + "/" + src.name;
  }
  return out;
}

/// Largest differences found between two projects, field by field.
struct Diff {
  size_t records_a = 0, records_b = 0, unmatched = 0;
  size_t vossels_a = 0, vossels_b = 0, vossel_mismatch = 0;
  double value = 0, range = 0, cos_inc = 0, foot = 0, uv = 0, vis = 0, conf = 0;
  double centroid = 0, normal = 0, frame = 0, fused = 0;
  int flags = 0;
  void Print(const char* what) const {
    std::printf("%s: %zu vs %zu vossels (%zu differ), %zu vs %zu records (%zu unmatched); max |Δ| "
                "value %.3g range %.3g cos %.3g foot %.3g uv %.3g vis %.3g conf %.3g centroid "
                "%.3g normal %.3g frame %.3g fused %.3g flags %d\n",
                what, vossels_a, vossels_b, vossel_mismatch, records_a, records_b, unmatched,
                value, range, cos_inc, foot, uv, vis, conf, centroid, normal, frame, fused, flags);
  }
};

/// Compares HEAD (or a version) of two projects: geometry by vossel coordinate, records by
/// (vossel coordinate, source name), fused colour by vossel.
Diff CompareProjects(const store::ProjectStore& sa, int64_t va, const store::ProjectStore& sb,
                     int64_t vb) {
  auto a = *sa.LoadSnapshot(va);
  auto b = *sb.LoadSnapshot(vb);
  const auto names_a = SourceNames(sa), names_b = SourceNames(sb);
  Diff d;
  d.vossels_a = a->geometry.size();
  d.vossels_b = b->geometry.size();
  d.records_a = a->records.size();
  d.records_b = b->records.size();
  auto key = [](const openvdb::Coord& c) { return std::make_tuple(c.x(), c.y(), c.z()); };
  std::map<std::tuple<int, int, int>, size_t> vb_of;
  for (size_t v = 0; v < b->geometry.size(); ++v) vb_of[key(b->geometry.coord[v])] = v;
  std::map<std::tuple<int, int, int, std::string>, size_t> rb_of;
  for (size_t i = 0; i < b->records.size(); ++i) {
    const auto c = b->geometry.coord[size_t(b->records.vossel[i])];
    rb_of[{c.x(), c.y(), c.z(), names_b.at(b->records.scan[i])}] = i;
  }
  const auto& fa = a->fused.by_modality.at(records::Modality::kRgb);
  const auto& fb = b->fused.by_modality.at(records::Modality::kRgb);
  for (size_t v = 0; v < a->geometry.size(); ++v) {
    auto it = vb_of.find(key(a->geometry.coord[v]));
    if (it == vb_of.end() || a->geometry.point_count[v] != b->geometry.point_count[it->second]) {
      ++d.vossel_mismatch;
      continue;
    }
    const size_t w = it->second;
    d.centroid = std::max(d.centroid, double((a->geometry.centroid_m[v] - b->geometry.centroid_m[w]).norm()));
    d.normal = std::max(d.normal, double((a->geometry.normal[v] - b->geometry.normal[w]).norm()));
    const records::VosselFrame& fa_v = a->geometry.frame.at(v);
    const records::VosselFrame& fb_w = b->geometry.frame.at(w);
    d.frame = std::max({d.frame, double((fa_v.centroid_m - fb_w.centroid_m).norm()),
                        double((fa_v.normal - fb_w.normal).norm()),
                        double(std::abs(fa_v.count - fb_w.count))});
    for (int c = 0; c < 3; ++c) {
      d.fused = std::max(d.fused, double(std::abs(fa.value[3 * v + c] - fb.value[3 * w + c])));
    }
  }
  const records::RecordSet& ra = a->records;
  const records::RecordSet& rb = b->records;
  for (size_t i = 0; i < ra.size(); ++i) {
    const auto c = a->geometry.coord[size_t(ra.vossel[i])];
    auto it = rb_of.find({c.x(), c.y(), c.z(), names_a.at(ra.scan[i])});
    if (it == rb_of.end()) {
      ++d.unmatched;
      continue;
    }
    const size_t j = it->second;
    for (int k = 0; k < records::kValueChannels; ++k) {
      d.value = std::max(d.value, double(std::abs(ra.value[3 * i + k] - rb.value[3 * j + k])));
    }
    d.range = std::max(d.range, double(std::abs(ra.range_m[i] - rb.range_m[j])));
    d.cos_inc = std::max(d.cos_inc, double(std::abs(ra.cos_inc[i] - rb.cos_inc[j])));
    d.foot = std::max({d.foot, double(std::abs(ra.foot_major_m[i] - rb.foot_major_m[j])),
                       double(std::abs(ra.foot_minor_m[i] - rb.foot_minor_m[j]))});
    d.uv = std::max({d.uv, double(std::abs(ra.uv_px[2 * i] - rb.uv_px[2 * j])),
                     double(std::abs(ra.uv_px[2 * i + 1] - rb.uv_px[2 * j + 1]))});
    d.vis = std::max(d.vis, double(std::abs(ra.vis[i] - rb.vis[j])));
    for (int k = 0; k < records::kConfidenceCount; ++k) {
      const size_t a = records::kConfidenceCount * i + k, b = records::kConfidenceCount * j + k;
      d.conf = std::max(d.conf, double(std::abs(ra.conf[a] - rb.conf[b])));
    }
    d.flags |= ra.flags[i] ^ rb.flags[j];
    d.flags |= ra.modality[i] ^ rb.modality[j];
  }
  return d;
}

/// The same project, record by record: every field equal to the bit (both sides went through
/// the same codecs from the same inputs, so any difference is a difference of inputs).
void ExpectSame(const Diff& d) {
  EXPECT_EQ(d.vossels_a, d.vossels_b);
  EXPECT_EQ(d.vossel_mismatch, 0u);
  EXPECT_EQ(d.records_a, d.records_b);
  EXPECT_EQ(d.unmatched, 0u);
  EXPECT_EQ(d.value, 0.0);
  EXPECT_EQ(d.range, 0.0);
  EXPECT_EQ(d.cos_inc, 0.0);
  EXPECT_EQ(d.foot, 0.0);
  EXPECT_EQ(d.uv, 0.0);
  EXPECT_EQ(d.vis, 0.0);
  EXPECT_EQ(d.conf, 0.0);
  EXPECT_EQ(d.centroid, 0.0);
  EXPECT_EQ(d.normal, 0.0);
  EXPECT_EQ(d.frame, 0.0);
  EXPECT_EQ(d.fused, 0.0);
  EXPECT_EQ(d.flags, 0);
}

std::unique_ptr<Engine> OpenEngine(const fs::path& root) {
  auto engine = Engine::Open(root);
  EXPECT_TRUE(engine.ok()) << engine.status();
  return std::move(*engine);
}

void CreateProject(Engine& engine, const std::string& name) {
  store::ProjectSettings settings;
  settings.vossel_size_m = kVosselM;
  settings.keep_versions = 20;
  ASSERT_TRUE(engine.CreateProject(name, settings).ok());
}

void Ingest(Engine& engine, const std::string& project, const ingest::ScanInput& scan) {
  auto r = engine.IngestScan(project, scan);
  ASSERT_TRUE(r.ok()) << r.status();
  std::printf("  %s <- %s: v%lld, %lld vossels, %lld records, %.2f s, %lld sources computed, "
              "%lld revisited on %lld (source, tile) pairs, %lld tiles and %lld bytes written\n",
              project.c_str(), scan.scan_name.c_str(), (long long)r->version,
              (long long)r->vossel_count, (long long)r->record_count, r->seconds,
              (long long)r->sources_computed, (long long)r->sources_revisited,
              (long long)r->pairs_revisited, (long long)r->tiles_changed,
              (long long)r->bytes_written);
}

std::unique_ptr<store::ProjectStore> OpenStore(const fs::path& root, const std::string& name) {
  auto st = store::ProjectStore::Open(root / name);
  EXPECT_TRUE(st.ok()) << st.status();
  return std::move(*st);
}

// Rebuilds project "room" (its next version) and expects it to equal version `incremental`.
void ExpectRebuildEquals(Engine& engine, const fs::path& root, int64_t incremental,
                         const char* what) {
  auto rebuilt = engine.Rebuild("room");
  ASSERT_TRUE(rebuilt.ok()) << rebuilt.status();
  ASSERT_EQ(rebuilt->version, incremental + 1);
  auto st = OpenStore(root, "room");
  const Diff d = CompareProjects(*st, incremental, *st, incremental + 1);
  d.Print(what);
  ExpectSame(d);
}

// The 8-bit RGB codes of PNG bytes, row-major, and their size; empty on failure (asserted).
std::vector<uint8_t> ReadRgb8(const std::string& png, int* w, int* h) {
  OIIO::Filesystem::IOMemReader reader(png.data(), png.size());
  OIIO::ImageSpec config;
  OIIO::Filesystem::IOProxy* proxy = &reader;
  config.attribute("oiio:ioproxy", OIIO::TypeDesc::PTR, &proxy);
  auto in = OIIO::ImageInput::open("in.png", &config);
  EXPECT_TRUE(in != nullptr) << OIIO::geterror();
  if (!in) return {};
  *w = in->spec().width;
  *h = in->spec().height;
  std::vector<uint8_t> rgb(size_t(*w) * size_t(*h) * 3);
  EXPECT_TRUE(in->read_image(0, 0, 0, 3, OIIO::TypeDesc::UINT8, rgb.data()));
  return rgb;
}

// 8-bit `pixels` (w × h × channels; with 4 channels the last is unassociated alpha) as PNG bytes.
std::string WritePng8(const std::vector<uint8_t>& pixels, int w, int h, int channels) {
  std::vector<unsigned char> buffer;
  OIIO::Filesystem::IOVecOutput out_proxy(buffer);
  auto out = OIIO::ImageOutput::create("out.png", &out_proxy);
  OIIO::ImageSpec spec(w, h, channels, OIIO::TypeDesc::UINT8);
  if (channels == 4) {
    spec.alpha_channel = 3;
    spec.attribute("oiio:UnassociatedAlpha", 1);
  }
  EXPECT_TRUE(out && out->open("out.png", spec) &&
              out->write_image(OIIO::TypeDesc::UINT8, pixels.data()) && out->close());
  return std::string(buffer.begin(), buffer.end());
}

// `pano`'s image (an 8-bit RGB PNG) with its nadir masked as a stitcher masks its tripod:
// transparent from row 0.75·H down, coverage ramping to it over the 6 rows above. `beside`: the
// image stays as it is and the coverage comes as a mask image beside it (a rig's mask); else
// the image becomes RGBA, black under the transparent pixels.
void MaskNadir(ingest::PanoramaData& pano, bool beside) {
  int w = 0, h = 0;
  const std::vector<uint8_t> rgb = ReadRgb8(pano.encoded_image, &w, &h);
  ASSERT_FALSE(rgb.empty());
  const int channels = beside ? 1 : 4;
  std::vector<uint8_t> out_pixels(size_t(w) * h * size_t(channels));
  const int cut = h * 3 / 4;
  for (size_t p = 0; p < size_t(w) * h; ++p) {
    const int row = int(p / size_t(w));
    const int a = row >= cut ? 0 : row < cut - 6 ? 255 : 255 * (cut - row) / 7;
    if (beside) {
      out_pixels[p] = uint8_t(a);
      continue;
    }
    for (int c = 0; c < 3; ++c) out_pixels[4 * p + size_t(c)] = a > 0 ? rgb[3 * p + size_t(c)] : 0;
    out_pixels[4 * p + 3] = uint8_t(a);
  }
  (beside ? pano.encoded_mask : pano.encoded_image) = WritePng8(out_pixels, w, h, channels);
}

// `pano`'s image (an 8-bit RGB PNG) cut to its top three quarters, sent as that part of its
// sphere (a camera without a nadir).
void KeepTopOfSphere(ingest::PanoramaData& pano) {
  int w = 0, h = 0;
  std::vector<uint8_t> rgb = ReadRgb8(pano.encoded_image, &w, &h);
  ASSERT_FALSE(rgb.empty());
  const int kept = h * 3 / 4;
  rgb.resize(size_t(w) * size_t(kept) * 3);  // row-major: the top rows
  pano.encoded_image = WritePng8(rgb, w, kept, 3);
  pano.sphere = ingest::SphereWindow{w, h, 0, 0};
}

// Ingests the room's 4 scans one at a time (their points coloured with `point_colour`), then
// rebuilds: the incremental HEAD is v4, the rebuild v5. `masked`: each panorama with its nadir
// transparent (MaskNadir), by its alpha at stations 0, by a mask beside it at 1 and 3, and
// left out of the image sent as a part of its sphere (KeepTopOfSphere) at 2.
void IngestRoomThenRebuild(const fs::path& root, bool point_colour, const char* what,
                           bool range_grid = false, bool masked = false) {
  auto engine = OpenEngine(root);
  CreateProject(*engine, "room");
  const scenes::SyntheticRoom room = scenes::SyntheticRoom::Default();
  for (size_t i = 0; i < room.Stations().size(); ++i) {
    const scenes::LidarSettings lidar = scenes::LidarSettings::Small(i + 1);
    auto scan = scenes::MakeScanInput(room, i, lidar, kPanoW, 2, point_colour);
    ASSERT_TRUE(scan.ok()) << scan.status();
    if (range_grid) scenes::SetRangeGrid(lidar, &scan->lidar);
    if (masked) {
      for (ingest::PanoramaData& pano : scan->panoramas) {
        if (i == 2) {
          ASSERT_NO_FATAL_FAILURE(KeepTopOfSphere(pano));
        } else {
          ASSERT_NO_FATAL_FAILURE(MaskNadir(pano, /*beside=*/i % 2 == 1));
        }
      }
    }
    Ingest(*engine, "room", *scan);
  }
  auto rebuilt = engine->Rebuild("room");
  ASSERT_TRUE(rebuilt.ok()) << rebuilt.status();
  std::printf("  rebuild: v%lld in %.2f s\n", (long long)rebuilt->version, rebuilt->seconds);
  auto st = OpenStore(root, "room");
  const Diff d = CompareProjects(*st, 4, *st, 5);
  d.Print(what);
  ExpectSame(d);
  if (masked) {  // the masks took: the floor under each camera is not its colour
    auto snap = st->LoadSnapshot(4);
    ASSERT_TRUE(snap.ok()) << snap.status();
    size_t invalidated = 0;
    for (size_t i = 0; i < (*snap)->records.size(); ++i) {
      invalidated += (*snap)->records.modality[i] == int8_t(records::Modality::kRgb) &&
                     ((*snap)->records.flags[i] & records::kFlagInvalidated) != 0;
    }
    std::printf("  %zu RGB records invalidated under the masks\n", invalidated);
    EXPECT_GT(invalidated, 1000u);
  }
  fs::remove_all(root);
}

// Claim (§5, flows.h): ingesting the room's 4 scans one at a time gives the same geometry,
// records and fused values, bit for bit, as a rebuild of the same scans from their blobs.
TEST(IncrementalTest, IngestOneAtATimeEqualsRebuildOnTheRoom) {
  IngestRoomThenRebuild(TestRoot("room"), false, "room: incremental v4 vs rebuild v5");
}

// Claim (flows.h): the same with coloured scans (per-point colour, a source of its own whose
// records are recomputed from its LiDAR's blob and its own): incremental equals rebuild.
TEST(IncrementalTest, IngestOfColouredScansEqualsRebuild) {
  IngestRoomThenRebuild(TestRoot("coloured"), true, "coloured room: incremental v4 vs rebuild v5");
}

// Claim (voxelise.h): the same with coloured scans with range grids, whose gap fill is binned
// with the returns and sampled by the LiDAR and its colour source on every path (ingest from
// the rig's input, rebuild from the stored blob with its grid).
TEST(IncrementalTest, IngestOfScansWithRangeGridsEqualsRebuild) {
  IngestRoomThenRebuild(TestRoot("grid"), true, "gridded coloured room: incremental v4 vs "
                        "rebuild v5", true);
}

// Claim (flows.h, sample.h): the same with panoramas whose nadir is transparent (alpha, a mask
// beside the image, or an image of part of the sphere), their coverage read alike on every
// path (the scan's own cameras, revisits through the image cache, the rebuild from the stored
// image and mask blobs).
TEST(IncrementalTest, IngestOfMaskedPanoramasEqualsRebuild) {
  IngestRoomThenRebuild(TestRoot("masked"), false, "masked room: incremental v4 vs rebuild v5",
                        false, true);
}

// Claim (§2.2, §5, flows.h): a camera-only scan (a pinhole photo and a panorama, where no
// LiDAR stood) between LiDAR scans is revisited like any camera when later scans change what it
// sees, the photo only within its field: incremental equals rebuild bit for bit.
TEST(IncrementalTest, CameraOnlyScanBetweenLidarScansEqualsRebuild) {
  const fs::path root = TestRoot("camera-only");
  auto engine = OpenEngine(root);
  CreateProject(*engine, "room");
  const scenes::SyntheticRoom room = scenes::SyntheticRoom::Default();
  auto cameras = scenes::MakeCameraOnlyScan(
      room, "cameras", scenes::LookAt(room.NovelViews()[0].o_world, {3.0, 3.3, 0.9}),
      room.NovelViews()[1], kPanoW);
  ASSERT_TRUE(cameras.ok()) << cameras.status();
  for (size_t i = 0; i < room.Stations().size(); ++i) {
    if (i == 2) Ingest(*engine, "room", *cameras);
    auto scan = scenes::MakeScanInput(room, i, scenes::LidarSettings::Small(i + 1), kPanoW, 2);
    ASSERT_TRUE(scan.ok()) << scan.status();
    Ingest(*engine, "room", *scan);
  }
  ExpectRebuildEquals(*engine, root, 5, "room with a camera-only scan: incremental v5 vs "
                      "rebuild v6");
  fs::remove_all(root);
}

// Claim (§5, flows.h): the same on a second site, a corridor of 4 rooms with 12 stations over
// several tiles, where a scan reaches only part of the site: incremental equals rebuild bit for
// bit, and older sources are recomputed only on the tiles the change can reach.
TEST(IncrementalTest, IngestOneAtATimeEqualsRebuildOnTheCorridor) {
  const fs::path root = TestRoot("corridor");
  auto engine = OpenEngine(root);
  CreateProject(*engine, "corridor");
  const scenes::CorridorSite site = scenes::CorridorSite::Default();
  ASSERT_GE(site.Stations().size(), 12u);
  int64_t revisited_last_half = 0, pairs_last_half = 0, blocks_last_half = 0, refreshed = 0;
  int64_t vossels_last_half = 0, in_blocks_last_half = 0;
  for (size_t i = 0; i < site.Stations().size(); ++i) {
    auto scan = scenes::MakeScanInput(site, i, scenes::LidarSettings::Small(i + 1), kPanoW, 2);
    ASSERT_TRUE(scan.ok()) << scan.status();
    auto r = engine->IngestScan("corridor", *scan);
    ASSERT_TRUE(r.ok()) << r.status();
    std::printf("  corridor <- %s: v%lld, %lld vossels, %lld records, %.2f s; %lld older sources "
                "revisited on %lld (source, tile) pairs; %lld tiles, %lld bytes written\n",
                scan->scan_name.c_str(), (long long)r->version, (long long)r->vossel_count,
                (long long)r->record_count, r->seconds, (long long)r->sources_revisited,
                (long long)r->pairs_revisited, (long long)r->tiles_changed,
                (long long)r->bytes_written);
    refreshed += r->sources_refreshed;
    if (i >= site.Stations().size() / 2) {
      revisited_last_half += r->sources_revisited;
      pairs_last_half += r->pairs_revisited;
      blocks_last_half += r->blocks_revisited;
      vossels_last_half += r->vossels_revisited;
      in_blocks_last_half += r->vossels_in_blocks;
    }
  }
  const int64_t n = int64_t(site.Stations().size());
  auto rebuilt = engine->Rebuild("corridor");
  ASSERT_TRUE(rebuilt.ok()) << rebuilt.status();
  std::printf("  rebuild: v%lld in %.2f s\n", (long long)rebuilt->version, rebuilt->seconds);
  auto st = OpenStore(root, "corridor");
  EXPECT_GE(st->LoadManifest(n)->tiles.size(), 6u);
  const Diff d = CompareProjects(*st, n, *st, n + 1);
  d.Print("corridor: incremental vs rebuild");
  ExpectSame(d);
  // The invariant the revisit rules rest on (change.h): every cell of a source's stored reach
  // raster bounds from above the depths the rebuild computes from the whole lattice.
  {
    auto inc = *st->LoadSnapshot(n);
    auto full = *st->LoadSnapshot(n + 1);
    size_t cells = 0, below = 0, tighter_equal = 0;
    for (const auto& [source, exact] : full->reach) {
      const tiles::ReachRaster& bound = inc->reach.at(source);
      ASSERT_EQ(bound.max_depth_m.size(), exact.max_depth_m.size());
      for (size_t c = 0; c < exact.max_depth_m.size(); ++c) {
        ++cells;
        below += bound.max_depth_m[c] < exact.max_depth_m[c] ? 1 : 0;
        tighter_equal += bound.max_depth_m[c] == exact.max_depth_m[c] ? 1 : 0;
      }
    }
    std::printf("  reach rasters: %zu cells, %zu equal to the rebuild's, %zu below it\n", cells,
                tighter_equal, below);
    EXPECT_EQ(below, 0u);
  }
  // Revisits are per (source, tile): the older sources a scan reaches are recomputed on part of
  // the site only. (How many sources a scan reaches is the model's answer, not a tuning knob:
  // at grazing incidence §5's slope-scaled tolerance lets a sensor's visibility test reach
  // past a 12 cm partition, so most older sources see some change.)
  const int64_t tiles = int64_t(st->LoadManifest(n)->tiles.size());
  int64_t older_sources_last_half = 0;  // 2 sources (LiDAR, camera) per earlier scan
  for (int64_t i = n / 2; i < n; ++i) older_sources_last_half += 2 * i;
  std::printf("  last %lld scans revisited %lld of %lld older sources, on %lld of %lld "
              "(source, tile) pairs, %lld (source, block) pairs\n",
              (long long)(n - n / 2), (long long)revisited_last_half,
              (long long)older_sources_last_half, (long long)pairs_last_half,
              (long long)(revisited_last_half * tiles), (long long)blocks_last_half);
  EXPECT_LT(pairs_last_half, revisited_last_half * tiles * 9 / 10);
  // Within a revisited block only the vossels whose tests a changed splat reaches are
  // recomputed (change.h rule 3), a minority of those the blocks hold; the equality with the
  // rebuild above is what shows the cut exact.
  std::printf("  %lld (source, vossel) pairs recomputed of the %lld those blocks hold\n",
              (long long)vossels_last_half, (long long)in_blocks_last_half);
  EXPECT_LT(vossels_last_half, in_blocks_last_half / 2);
  // Some of those revisits refreshed their source's records without its blob (RefreshedRecords),
  // and the project still equals the rebuild above.
  std::printf("  %lld older sources refreshed from their own records over the %lld scans\n",
              (long long)refreshed, (long long)n);
  EXPECT_GT(refreshed, 0);
  fs::remove_all(root);
}

// Claim (records.h VosselFrame, change.h): a scan that re-observes geometry the project holds
// (here the same station captured again) grows the surface of every vossel it sees but leaves
// their record frames as they were, so no older source is revisited and every older record is
// kept bit for bit; and the result still equals a rebuild.
TEST(IncrementalTest, RescanningKnownGeometryRevisitsNothing) {
  const fs::path root = TestRoot("rescan");
  auto engine = OpenEngine(root);
  CreateProject(*engine, "room");
  const scenes::SyntheticRoom room = scenes::SyntheticRoom::Default();
  auto first = scenes::MakeScanInput(room, 0, scenes::LidarSettings::Small(1), kPanoW, 2);
  ASSERT_TRUE(first.ok()) << first.status();
  Ingest(*engine, "room", *first);
  ingest::ScanInput again = *first;
  again.scan_name = "station-0-again";
  auto r = engine->IngestScan("room", again);
  ASSERT_TRUE(r.ok()) << r.status();
  std::printf("  rescan: %lld older sources revisited on %lld blocks; %lld tiles written\n",
              (long long)r->sources_revisited, (long long)r->blocks_revisited,
              (long long)r->tiles_changed);
  EXPECT_EQ(r->sources_revisited, 0);
  EXPECT_EQ(r->blocks_revisited, 0);
  auto st = OpenStore(root, "room");
  auto one = *st->LoadSnapshot(1);
  auto two = *st->LoadSnapshot(2);
  ASSERT_EQ(one->geometry.size(), two->geometry.size());
  size_t doubled = 0;
  for (size_t v = 0; v < one->geometry.size(); ++v) {
    doubled += two->geometry.point_count[v] == 2 * one->geometry.point_count[v] ? 1 : 0;
    EXPECT_TRUE(two->geometry.frame[v] == one->geometry.frame[v]) << "vossel " << v;
  }
  EXPECT_EQ(doubled, one->geometry.size());
  // Scan 1's records in version 2 are those of version 1, field by field.
  std::vector<size_t> older;
  for (size_t i = 0; i < two->records.size(); ++i) {
    if (two->records.batch[i] == one->records.batch[0]) older.push_back(i);
  }
  const records::RecordSet kept = two->records.Select(older);
  ASSERT_EQ(kept.size(), one->records.size());
  EXPECT_EQ(kept.vossel, one->records.vossel);
  EXPECT_EQ(kept.value, one->records.value);
  EXPECT_EQ(kept.range_m, one->records.range_m);
  EXPECT_EQ(kept.cos_inc, one->records.cos_inc);
  EXPECT_EQ(kept.uv_px, one->records.uv_px);
  EXPECT_EQ(kept.vis, one->records.vis);
  auto rebuilt = engine->Rebuild("room");
  ASSERT_TRUE(rebuilt.ok()) << rebuilt.status();
  st = OpenStore(root, "room");
  const Diff d = CompareProjects(*st, 2, *st, 3);
  d.Print("rescan: incremental v2 vs rebuild v3");
  ExpectSame(d);
  fs::remove_all(root);
}

// Claim (flows.h): deleting scan k of N gives the same project, record by record, as
// ingesting the other N−1 scans alone (sources matched by scan and source name).
TEST(IncrementalTest, DeleteEqualsIngestingTheOthers) {
  const fs::path root = TestRoot("delete");
  auto engine = OpenEngine(root);
  CreateProject(*engine, "all");
  CreateProject(*engine, "others");
  const scenes::SyntheticRoom room = scenes::SyntheticRoom::Default();
  const size_t doomed = 1;  // station 1 lights the region station 0 sees shadowed
  for (size_t i = 0; i < room.Stations().size(); ++i) {
    auto scan = scenes::MakeScanInput(room, i, scenes::LidarSettings::Small(i + 1), kPanoW, 2);
    ASSERT_TRUE(scan.ok()) << scan.status();
    Ingest(*engine, "all", *scan);
    if (i != doomed) Ingest(*engine, "others", *scan);
  }
  auto deleted = engine->DeleteScan("all", "scan-" + std::to_string(doomed + 1));
  ASSERT_TRUE(deleted.ok()) << deleted.status();
  std::printf("  delete scan-%zu: v%lld in %.2f s, %lld sources revisited on %lld pairs\n",
              doomed + 1, (long long)deleted->version, deleted->seconds,
              (long long)deleted->sources_revisited, (long long)deleted->pairs_revisited);
  EXPECT_EQ(engine->DeleteScan("all", "scan-" + std::to_string(doomed + 1)).status().code(),
            absl::StatusCode::kNotFound);
  auto all = OpenStore(root, "all");
  auto others = OpenStore(root, "others");
  EXPECT_EQ(all->ListScans()->size(), room.Stations().size() - 1);
  const Diff d = CompareProjects(*all, all->head_version(), *others, others->head_version());
  d.Print("room: delete scan-2 of 4 vs ingest of the 3 others");
  ExpectSame(d);
  // The deleted scan's blobs stay while a kept version has it.
  EXPECT_TRUE(all->LoadSnapshot(all->head_version() - 1).ok());
  fs::remove_all(root);
}

/// Points on the surface of `box` (every face but the bottom), a grid of pitch `step_m`, in the
/// sensor frame of `pose`: a LiDAR that sees the new object alone.
ingest::ScanInput BoxOnlyScan(const scenes::Aabb& box, const geometry::Pose& pose, double step_m) {
  ingest::ScanInput scan;
  scan.scan_name = "box";
  scan.pose = pose;
  scan.lidar.divergence_rad = 3e-4;
  const Eigen::Matrix3d R_sensor_world = pose.q_world_sensor.conjugate().toRotationMatrix();
  auto add = [&](const Eigen::Vector3d& x) {
    const Eigen::Vector3d p = R_sensor_world * (x - pose.o_world);
    for (int c = 0; c < 3; ++c) scan.lidar.xyz_sensor_m.push_back(float(p[c]));
    scan.lidar.intensity.push_back(0.5f);
  };
  const Eigen::Vector3d lo = box.min_m, hi = box.max_m;
  for (int axis = 0; axis < 3; ++axis) {
    const int u = (axis + 1) % 3, v = (axis + 2) % 3;
    for (int side = 0; side < 2; ++side) {
      if (axis == 2 && side == 0) continue;  // the bottom rests on the floor
      for (double a = lo[u]; a <= hi[u] + 1e-9; a += step_m) {
        for (double b = lo[v]; b <= hi[v] + 1e-9; b += step_m) {
          Eigen::Vector3d x;
          x[axis] = side ? hi[axis] : lo[axis];
          x[u] = a;
          x[v] = b;
          add(x);
        }
      }
    }
  }
  return scan;
}

/// True when the segment o → x passes through `box` grown by `grow_m`.
bool SegmentHitsBox(const Eigen::Vector3d& o, const Eigen::Vector3d& x, const scenes::Aabb& box,
                    double grow_m) {
  double t0 = 0.0, t1 = 1.0;
  const Eigen::Vector3d d = x - o;
  for (int a = 0; a < 3; ++a) {
    const double lo = box.min_m[a] - grow_m, hi = box.max_m[a] + grow_m;
    if (std::abs(d[a]) < 1e-12) {
      if (o[a] < lo || o[a] > hi) return false;
      continue;
    }
    double ta = (lo - o[a]) / d[a], tb = (hi - o[a]) / d[a];
    if (ta > tb) std::swap(ta, tb);
    t0 = std::max(t0, ta);
    t1 = std::min(t1, tb);
    if (t0 > t1) return false;
  }
  return true;
}

// Project "room" with the room's first two scans.
void IngestTwoRoomScans(Engine& engine, const scenes::SyntheticRoom& room) {
  CreateProject(engine, "room");
  for (size_t i = 0; i < 2; ++i) {
    auto scan = scenes::MakeScanInput(room, i, scenes::LidarSettings::Small(i + 1), kPanoW, 2);
    ASSERT_TRUE(scan.ok()) << scan.status();
    Ingest(engine, "room", *scan);
  }
}

// A 0.6 m cube between the room's stations and wall x = max, away from the room's own box.
scenes::Aabb CubeBeforeTheWall(const scenes::SyntheticRoom& room) {
  const scenes::Aabb& bounds = room.RoomBounds();
  scenes::Aabb cube;
  cube.min_m = Eigen::Vector3d(bounds.max_m.x() - 1.4, bounds.min_m.y() + 1.2, 0.6);
  cube.max_m = cube.min_m + Eigen::Vector3d(0.6, 0.6, 0.6);
  return cube;
}

// A scan of that cube alone, from a station beside it.
ingest::ScanInput CubeScan(const scenes::SyntheticRoom& room) {
  const scenes::Aabb& bounds = room.RoomBounds();
  geometry::Pose pose;
  pose.o_world = Eigen::Vector3d(bounds.max_m.x() - 2.5, bounds.min_m.y() + 2.6, 1.4);
  return BoxOnlyScan(CubeBeforeTheWall(room), pose, 0.01);
}

// Claim (§5): adding a scan that puts a new object in front of older scans' walls turns exactly
// the older records behind it to shadow: every older record whose line of sight the object
// blocks (by more than the vossel and footprint margins) is gone, and every other older record
// away from the object's own neighbourhood is bit-identical.
TEST(IncrementalTest, NewObjectShadowsExactlyTheRecordsBehindIt) {
  const fs::path root = TestRoot("revis");
  auto engine = OpenEngine(root);
  const scenes::SyntheticRoom room = scenes::SyntheticRoom::Default();
  ASSERT_NO_FATAL_FAILURE(IngestTwoRoomScans(*engine, room));
  auto st = OpenStore(root, "room");
  auto before = *st->LoadSnapshot(2);
  std::map<int32_t, Eigen::Vector3d> origin;
  const std::vector<store::ScanInfo> scans = *st->ListScans();
  for (const store::ScanInfo& s : scans) {
    for (const store::SourceInfo& src : s.sources) origin[src.id] = src.pose.o_world;
  }
  const scenes::Aabb cube = CubeBeforeTheWall(room);
  Ingest(*engine, "room", CubeScan(room));
  st = OpenStore(root, "room");
  auto after = *st->LoadSnapshot(3);

  auto key = [](const openvdb::Coord& c, int32_t scan) {
    return std::make_tuple(c.x(), c.y(), c.z(), scan);
  };
  std::map<std::tuple<int, int, int, int32_t>, size_t> after_of;
  for (size_t i = 0; i < after->records.size(); ++i) {
    after_of[key(after->geometry.coord[size_t(after->records.vossel[i])], after->records.scan[i])] = i;
  }
  const double h = kVosselM;
  size_t behind = 0, behind_gone = 0, clear = 0, clear_same = 0, near_object = 0;
  for (size_t i = 0; i < before->records.size(); ++i) {
    const size_t v = size_t(before->records.vossel[i]);
    const Eigen::Vector3d x = before->geometry.centroid_m[v].cast<double>();
    const int32_t scan = before->records.scan[i];
    auto it = after_of.find(key(before->geometry.coord[v], scan));
    if (SegmentHitsBox(origin.at(scan), x, cube, 3 * h) && !SegmentHitsBox(x, x, cube, 3 * h)) {
      if (!SegmentHitsBox(origin.at(scan), x, cube, -2 * h)) continue;  // the penumbra band
      ++behind;
      behind_gone += it == after_of.end() ? 1 : 0;
      continue;
    }
    if (SegmentHitsBox(x, x, cube, 3 * h)) {  // the object's own neighbourhood: normals move
      ++near_object;
      continue;
    }
    ++clear;
    if (it == after_of.end()) continue;
    const size_t j = it->second;
    bool same = before->records.vis[i] == after->records.vis[j] &&
                before->records.range_m[i] == after->records.range_m[j] &&
                before->records.cos_inc[i] == after->records.cos_inc[j];
    for (int c = 0; c < 3; ++c) same = same && before->records.value[3 * i + c] == after->records.value[3 * j + c];
    clear_same += same ? 1 : 0;
  }
  std::printf("new object: %zu older records behind it, %zu turned to shadow; %zu clear of it, "
              "%zu unchanged; %zu in its neighbourhood\n",
              behind, behind_gone, clear, clear_same, near_object);
  EXPECT_GT(behind, 300u);
  EXPECT_EQ(behind_gone, behind);
  EXPECT_GT(clear, 10000u);
  EXPECT_EQ(clear_same, clear);
  fs::remove_all(root);
}

// Claim (change.h RefreshedRecords): where a change only moves visibility, an older LiDAR's
// records are refreshed from themselves without its points. A cube put in front of the room's
// walls appears where neither older LiDAR has a return and changes no frame of theirs, so both
// are refreshed: their blobs are moved away for that ingest and it still succeeds. The cameras
// see the cube's new faces and read their images. Then the project equals a rebuild.
TEST(IncrementalTest, VisibilityOnlyChangeRefreshesOlderLidarsWithoutTheirPoints) {
  const fs::path root = TestRoot("refresh");
  auto engine = OpenEngine(root);
  const scenes::SyntheticRoom room = scenes::SyntheticRoom::Default();
  ASSERT_NO_FATAL_FAILURE(IngestTwoRoomScans(*engine, room));
  // The LiDARs' point blobs, moved aside: a revisit that read one would fail.
  std::vector<std::string> moved;
  const std::vector<store::ScanInfo> scans = *OpenStore(root, "room")->ListScans();
  for (const store::ScanInfo& s : scans) {
    for (const store::SourceInfo& src : s.sources) {
      if (src.modality != records::Modality::kLidar) continue;
      fs::rename(root / "room" / "blobs" / src.blob_sha256, root / src.blob_sha256);
      moved.push_back(src.blob_sha256);
    }
  }
  ASSERT_EQ(moved.size(), 2u);
  auto r = engine->IngestScan("room", CubeScan(room));
  ASSERT_TRUE(r.ok()) << r.status();
  std::printf("  cube: %lld older sources revisited, %lld refreshed without their blob\n",
              (long long)r->sources_revisited, (long long)r->sources_refreshed);
  EXPECT_EQ(r->sources_refreshed, 2);
  EXPECT_GT(r->sources_revisited, r->sources_refreshed);  // a camera sees the cube's faces
  for (const std::string& sha : moved) fs::rename(root / sha, root / "room" / "blobs" / sha);
  ExpectRebuildEquals(*engine, root, 3, "cube: incremental v3 vs rebuild v4");
  fs::remove_all(root);
}

// Of the projects "all" (every scan) and "others" (every scan but scan `doomed`, 0-based): a
// rebuild of "all" equals its HEAD, and deleting scan `doomed` from "all" equals "others", record
// by record.
void ExpectRebuildAndDeleteEqual(Engine& engine, const fs::path& root, size_t doomed,
                                 const std::string& what) {
  auto rebuilt = engine.Rebuild("all");
  ASSERT_TRUE(rebuilt.ok()) << rebuilt.status();
  {
    auto all = OpenStore(root, "all");
    const Diff d = CompareProjects(*all, rebuilt->version - 1, *all, rebuilt->version);
    d.Print((what + ": incremental vs rebuild").c_str());
    ExpectSame(d);
    EXPECT_GT(d.records_a, 0u);
  }
  auto deleted = engine.DeleteScan("all", "scan-" + std::to_string(doomed + 1));
  ASSERT_TRUE(deleted.ok()) << deleted.status();
  auto all = OpenStore(root, "all");
  auto others = OpenStore(root, "others");
  const Diff d = CompareProjects(*all, all->head_version(), *others, others->head_version());
  d.Print((what + ": delete vs ingest of the others").c_str());
  ExpectSame(d);
}

// Claims of flows.h on sites nobody laid out: a seeded random room of oriented boxes (plates
// thinner than a vossel, floating and tilted boxes, boxes through walls) scanned from stations
// at random places with tilted sensors (RandomSite), a camera-only scan of a tilted pinhole
// photo and panorama, and a render sent back (§10) before the last station. Ingesting its scans
// one at a time equals a rebuild, record by record, and deleting one of them equals ingesting
// the others; some seeds send coloured points, some range grids.
class RandomSiteTest : public ::testing::TestWithParam<uint64_t> {};

TEST_P(RandomSiteTest, IngestOneAtATimeEqualsRebuildAndDeleteEqualsTheOthers) {
  const uint64_t seed = GetParam();
  const scenes::RandomSite site(seed, /*boxes=*/6, /*stations=*/5);
  ASSERT_EQ(site.Stations().size(), 5u) << "seed " << seed << " has no room for its stations";
  const bool point_colour = seed % 2 == 0, range_grid = seed % 3 == 0;
  const size_t doomed = size_t(seed % site.Stations().size());
  std::printf("  seed %llu: room %.2f x %.2f x %.2f m, %zu boxes, point colour %d, range grid "
              "%d, deleting scan-%zu\n",
              (unsigned long long)seed, site.Bounds().max_m.x() - site.Bounds().min_m.x(),
              site.Bounds().max_m.y() - site.Bounds().min_m.y(),
              site.Bounds().max_m.z() - site.Bounds().min_m.z(), site.Boxes().size(),
              int(point_colour), int(range_grid), doomed + 1);
  const fs::path root = TestRoot("random-" + std::to_string(seed));
  auto engine = OpenEngine(root);
  CreateProject(*engine, "all");
  CreateProject(*engine, "others");
  // A camera-only scan between the third and fourth stations: a tilted pinhole photo of the
  // first box and a tilted panorama, from the site's novel views.
  ASSERT_EQ(site.NovelViews().size(), 2u);
  auto cameras = scenes::MakeCameraOnlyScan(
      site, "cameras", scenes::LookAt(site.NovelViews()[0].o_world, site.Boxes()[0].centre_m),
      site.NovelViews()[1], kPanoW);
  ASSERT_TRUE(cameras.ok()) << cameras.status();
  for (size_t i = 0; i < site.Stations().size(); ++i) {
    if (i == 3) {
      ASSERT_NO_FATAL_FAILURE(Ingest(*engine, "all", *cameras));
      ASSERT_NO_FATAL_FAILURE(Ingest(*engine, "others", *cameras));
    }
    if (i == 4) {  // a render from a tilted view sent back as derived data, into both projects
      RenderRequest req;
      req.pose = site.NovelViews()[0];
      req.width_px = kPanoW;
      req.height_px = kPanoW / 2;
      auto view = engine->Render("all", req);
      ASSERT_TRUE(view.ok()) << view.status();
      BackProjectInput in;
      in.name = "retouch";
      in.pose = req.pose;
      auto exr = render::EncodeExr(*view);
      ASSERT_TRUE(exr.ok()) << exr.status();
      in.image = *exr;
      for (const char* project : {"all", "others"}) {
        auto r = engine->BackProject(project, in);
        ASSERT_TRUE(r.ok()) << r.status();
        EXPECT_GT(r->pixels_back_projected, 0);
      }
    }
    const scenes::LidarSettings lidar = scenes::LidarSettings::Small(seed * 100 + i + 1);
    auto scan = scenes::MakeScanInput(site, i, lidar, kPanoW, 2, point_colour);
    ASSERT_TRUE(scan.ok()) << scan.status();
    if (range_grid) scenes::SetRangeGrid(lidar, &scan->lidar);
    ASSERT_NO_FATAL_FAILURE(Ingest(*engine, "all", *scan));
    if (i != doomed) ASSERT_NO_FATAL_FAILURE(Ingest(*engine, "others", *scan));
  }
  ExpectRebuildAndDeleteEqual(*engine, root, doomed, "random site");
  fs::remove_all(root);
}

INSTANTIATE_TEST_SUITE_P(Seeds, RandomSiteTest, ::testing::Values(1, 2, 3, 6));

// The same on an outdoor yard (RandomSite's `outdoor`): 30-60 m across, no ceiling (rays to the
// sky return nothing), far walls beyond the scanners' 50 m range, buildings of several metres,
// h = 10 cm; three stations, the second deleted.
TEST(RandomSiteTest, OutdoorYardIngestEqualsRebuildAndDeleteEqualsTheOthers) {
  const scenes::RandomSite site(11, /*boxes=*/8, /*stations=*/3, /*outdoor=*/true);
  ASSERT_EQ(site.Stations().size(), 3u);
  const fs::path root = TestRoot("yard");
  auto engine = OpenEngine(root);
  for (const char* name : {"all", "others"}) {
    store::ProjectSettings settings;
    settings.vossel_size_m = 0.10;
    settings.keep_versions = 20;
    ASSERT_TRUE(engine->CreateProject(name, settings).ok());
  }
  const size_t doomed = 1;
  for (size_t i = 0; i < site.Stations().size(); ++i) {
    scenes::LidarSettings lidar = scenes::LidarSettings::Small(i + 1);
    lidar.range_noise_m = 0.005;
    auto scan = scenes::MakeScanInput(site, i, lidar, kPanoW, 2, /*point_colour=*/true);
    ASSERT_TRUE(scan.ok()) << scan.status();
    scenes::SetRangeGrid(lidar, &scan->lidar);
    ASSERT_NO_FATAL_FAILURE(Ingest(*engine, "all", *scan));
    if (i != doomed) ASSERT_NO_FATAL_FAILURE(Ingest(*engine, "others", *scan));
  }
  ExpectRebuildAndDeleteEqual(*engine, root, doomed, "yard");
  fs::remove_all(root);
}

}  // namespace
}  // namespace vasl

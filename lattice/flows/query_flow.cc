// The query flows (flows.h): renders (§8) and provenance queries of a loaded version under a
// weighting profile (§7). They read; they never change a project.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <map>
#include <memory>
#include <tuple>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_format.h"
#include "lattice/flows/flows.h"
#include "lattice/flows/tile_budget.h"
#include "lattice/ingest/artefacts.h"
#include "lattice/fusion/fuse.h"
#include "lattice/ingest/sample.h"

namespace vasl::flows {
namespace {

/// Where each source stood, by source id (non-finite for unknown ids), and its scan.
struct SourceTable {
  std::vector<Eigen::Vector3d> origin_m;
  std::map<int32_t, std::pair<const store::ScanInfo*, const store::SourceInfo*>> by_id;
  std::vector<store::ScanInfo> scans;
};

absl::StatusOr<std::unique_ptr<SourceTable>> Sources(const store::ProjectStore& store,
                                                     int64_t version) {
  auto out = std::make_unique<SourceTable>();
  absl::StatusOr<std::vector<store::ScanInfo>> scans = store.ListScans(version);
  if (!scans.ok()) return scans.status();
  out->scans = std::move(*scans);
  for (const store::ScanInfo& scan : out->scans) {
    for (const store::SourceInfo& src : scan.sources) {
      if (src.id < 0) continue;
      if (size_t(src.id) >= out->origin_m.size()) {
        out->origin_m.resize(size_t(src.id) + 1, Eigen::Vector3d::Constant(NAN));
      }
      out->origin_m[size_t(src.id)] = src.pose.o_world;
      out->by_id[src.id] = {&scan, &src};
    }
  }
  return out;
}

}  // namespace

std::shared_ptr<const records::FusedValues> FusedLayerCache::Find(int64_t version,
                                                                  const std::string& layer) {
  std::lock_guard<std::mutex> lock(mu_);
  if (version != version_) return nullptr;
  auto it = layers_.find(layer);
  return it == layers_.end() ? nullptr : it->second;
}

void FusedLayerCache::Put(int64_t version, const std::string& layer,
                          std::shared_ptr<const records::FusedValues> values) {
  std::lock_guard<std::mutex> lock(mu_);
  if (version != version_ || layers_.size() >= 4) {
    layers_.clear();
    version_ = version;
  }
  layers_[layer] = std::move(values);
}

namespace {

/// `snapshot`'s fused values under `profile`: the default layer, a layer every tile holds, or
/// null when the version has none complete.
absl::StatusOr<std::shared_ptr<const records::FusedValues>> StoredFused(
    const store::ProjectStore& store, const std::shared_ptr<const store::Snapshot>& snap,
    const fusion::WeightingProfile& profile, FusedLayerCache& cache) {
  if (profile.name == fusion::kDefaultProfileName) {
    return std::shared_ptr<const records::FusedValues>(snap, &snap->fused);
  }
  const std::string layer = store::FusedLayerName(profile.name, profile.version);
  const std::vector<std::string> complete = store::CompleteProfileLayers(snap->manifest);
  if (std::find(complete.begin(), complete.end(), layer) == complete.end()) {
    return std::shared_ptr<const records::FusedValues>();
  }
  if (auto it = snap->profile_fused.find(layer); it != snap->profile_fused.end()) {
    return std::shared_ptr<const records::FusedValues>(snap, &it->second);
  }
  if (snap->partial) {  // the cache holds whole versions' layers: a partial one loads its own
    return absl::InternalError(
        absl::StrCat("a partial snapshot was loaded without the complete layer ", layer));
  }
  if (auto cached = cache.Find(snap->version, layer)) return cached;
  auto loaded = store.LoadSnapshot(snap->version, {layer}, /*with_records=*/false);
  if (!loaded.ok()) return loaded.status();
  auto values = std::make_shared<const records::FusedValues>((*loaded)->profile_fused.at(layer));
  cache.Put(snap->version, layer, values);
  return values;
}

}  // namespace

SourceImageCache::Entry SourceImageCache::Use(const std::string& key) {
  std::lock_guard<std::mutex> lock(mu_);
  auto it = entries_.find(key);
  if (it == entries_.end()) return Entry{};
  it->second.used = ++clock_;
  it->second.worth = inflation_ + it->second.cost_per_byte;
  return it->second;
}

std::shared_ptr<const geometry::LinearImage> SourceImageCache::Find(
    const std::string& key, std::shared_ptr<const ingest::ArtefactMaps>* artefacts) {
  Entry entry = Use(key);
  if (artefacts != nullptr) *artefacts = std::move(entry.artefacts);
  return std::move(entry.image);
}

SourceImageCache::Entry SourceImageCache::ImageEntry(
    int64_t image_bytes, std::shared_ptr<const ingest::ArtefactMaps> artefacts,
    double cost_seconds) {
  Entry entry;
  entry.bytes = image_bytes;
  if (artefacts != nullptr) {
    for (const geometry::LinearImage* map :
         {&artefacts->saturation.conf, &artefacts->smear.conf, &artefacts->flare.conf,
          &artefacts->codec.conf}) {
      entry.bytes += int64_t(map->ByteSize());
    }
  }
  entry.artefacts = std::move(artefacts);
  entry.cost_per_byte =
      std::max(0.0, cost_seconds) / double(std::max<int64_t>(1, entry.bytes));
  return entry;
}

void SourceImageCache::Put(const std::string& key,
                           std::shared_ptr<const geometry::LinearImage> image,
                           std::shared_ptr<const ingest::ArtefactMaps> artefacts,
                           double cost_seconds) {
  Entry entry = ImageEntry(int64_t(image->ByteSize()), std::move(artefacts), cost_seconds);
  entry.image = std::move(image);
  Keep(key, std::move(entry));
}

std::shared_ptr<const geometry::Srgb8Image> SourceImageCache::FindPacked(
    const std::string& key, std::shared_ptr<const ingest::ArtefactMaps>* artefacts) {
  Entry entry = Use(key);
  if (artefacts != nullptr) *artefacts = std::move(entry.artefacts);
  return std::move(entry.packed);
}

void SourceImageCache::PutPacked(const std::string& key,
                                 std::shared_ptr<const geometry::Srgb8Image> packed,
                                 std::shared_ptr<const ingest::ArtefactMaps> artefacts,
                                 double cost_seconds) {
  Entry entry = ImageEntry(int64_t(packed->ByteSize()), std::move(artefacts), cost_seconds);
  entry.packed = std::move(packed);
  Keep(key, std::move(entry));
}

std::shared_ptr<const ingest::LidarSource> SourceImageCache::FindLidar(const std::string& key) {
  return Use(key).lidar;
}

void SourceImageCache::PutLidar(const std::string& key,
                                std::shared_ptr<const ingest::LidarSource> lidar,
                                double cost_seconds) {
  Entry entry;
  entry.bytes = int64_t(sizeof(float) * (lidar->xyz_sensor_m.size() + lidar->intensity.size() +
                                         lidar->rgb.size()) +
                        sizeof(uint32_t) * lidar->grid_cell.size());
  if (lidar->gap_fill != nullptr) {
    entry.bytes += int64_t(lidar->gap_fill->size() *
                           (sizeof(Eigen::Vector3d) + sizeof(std::array<uint32_t, 3>) +
                            sizeof(std::array<float, 3>)));
  }
  entry.lidar = std::move(lidar);
  entry.cost_per_byte = std::max(0.0, cost_seconds) / double(std::max<int64_t>(1, entry.bytes));
  Keep(key, std::move(entry));
}

void SourceImageCache::Keep(const std::string& key, Entry entry) {
  if (entry.bytes > budget_bytes_) return;
  std::lock_guard<std::mutex> lock(mu_);
  if (entries_.count(key) != 0) return;
  while (bytes_ + entry.bytes > budget_bytes_ && !entries_.empty()) {
    auto oldest = entries_.begin();  // the least worth, the least recently used among equals
    for (auto it = entries_.begin(); it != entries_.end(); ++it) {
      if (std::tie(it->second.worth, it->second.used) <
          std::tie(oldest->second.worth, oldest->second.used)) {
        oldest = it;
      }
    }
    inflation_ = std::max(inflation_, oldest->second.worth);
    bytes_ -= oldest->second.bytes;
    entries_.erase(oldest);
  }
  bytes_ += entry.bytes;
  entry.used = ++clock_;
  entry.worth = inflation_ + entry.cost_per_byte;
  entries_[key] = std::move(entry);
}

namespace {

/// ColourDetail::kSourceImages: the images of the cameras whose weighted colour records lie on
/// the render's hit vossels, by source id, most-hit first within the cache's budget. Counts in
/// `*skipped` the cameras left out (beyond the budget).
absl::StatusOr<std::vector<render::DetailImage>> DetailImages(
    const store::ProjectStore& store, const SourceTable& sources, const records::RecordSet& recs,
    const fusion::RecordWeightsResult& weights, const render::RenderImage& image,
    const RenderCaches& caches, int64_t* skipped) {
  std::vector<int64_t> hits_of_vossel(weights.begin.size() - 1, 0);
  for (int32_t k : image.vossel_index) {
    if (k >= 0 && size_t(k) < hits_of_vossel.size()) ++hits_of_vossel[size_t(k)];
  }
  std::map<int32_t, int64_t> hits_of_source;
  for (size_t k = 0; k < hits_of_vossel.size(); ++k) {
    if (hits_of_vossel[k] == 0) continue;
    for (size_t i = weights.begin[k]; i < weights.begin[k + 1]; ++i) {
      if (records::Modality(recs.modality[i]) == records::Modality::kRgb && weights.weight[i] > 0) {
        hits_of_source[recs.scan[i]] += hits_of_vossel[k];
      }
    }
  }
  std::vector<std::pair<int64_t, const store::SourceInfo*>> cameras;  // (hits, source)
  for (const auto& [id, hits] : hits_of_source) {
    auto it = sources.by_id.find(id);
    if (it == sources.by_id.end()) continue;
    const store::SourceInfo* src = it->second.second;
    if (src->modality != records::Modality::kRgb || IsPointColour(*src) || src->width_px <= 0 ||
        src->blob_sha256.empty()) {
      continue;
    }
    cameras.emplace_back(hits, src);
  }
  std::sort(cameras.begin(), cameras.end(), [](const auto& a, const auto& b) {
    return a.first != b.first ? a.first > b.first : a.second->id < b.second->id;
  });
  std::vector<const store::SourceInfo*> chosen;
  int64_t bytes = 0;
  for (const auto& [hits, src] : cameras) {
    const int64_t need = DecodedImageBytes(*src);
    if (bytes + need > caches.images->budget_bytes()) {
      ++*skipped;
      continue;
    }
    bytes += need;
    chosen.push_back(src);
  }
  std::vector<render::DetailImage> out;
  for (const store::SourceInfo* src : chosen) {
    if (size_t(src->id) >= out.size()) out.resize(size_t(src->id) + 1);
  }
  std::vector<absl::Status> status(chosen.size());
  tbb::parallel_for(size_t(0), chosen.size(), [&](size_t c) {
    const store::SourceInfo& src = *chosen[c];
    std::shared_ptr<const geometry::LinearImage> img = caches.images->Find(DecodedImageKey(src));
    if (!img) {
      const auto t0 = std::chrono::steady_clock::now();
      const ingest::CameraSource cam = StoredCamera(store, src, 0, caches.max_image_pixels);
      absl::StatusOr<ingest::LinearImage> decoded = cam.load();
      if (!decoded.ok()) {
        status[c] = decoded.status();
        return;
      }
      // As its records read it (ingest::CameraRecords): fringing corrected (§9).
      ingest::CorrectChannelShift(*decoded, ingest::EstimateChannelShift(*decoded, !cam.pinhole));
      img = std::make_shared<const geometry::LinearImage>(std::move(*decoded));
      caches.images->Put(DecodedImageKey(src), img, nullptr,  // worth what its decode took
                         std::chrono::duration<double>(std::chrono::steady_clock::now() - t0)
                             .count());
    }
    render::DetailImage& d = out[size_t(src.id)];
    d.pose = src.pose;
    d.projection = ingest::ProjectionOf(CameraOf(src, 0), img->width_px, img->height_px);
    d.image = std::move(img);
  });
  for (const absl::Status& s : status) {
    if (!s.ok()) return s;
  }
  return out;
}

}  // namespace

namespace {

/// The render of `snap` (whole or partial) under `profile` that RenderQuery describes, not
/// recorded in the catalog.
absl::StatusOr<render::RenderImage> RenderSnapshot(store::ProjectStore& store,
                                                  std::shared_ptr<const store::Snapshot> snap,
                                                  const fusion::WeightingProfile& profile,
                                                  const render::RenderRequest& request,
                                                  const RenderCaches& caches) {
  absl::StatusOr<std::shared_ptr<const records::FusedValues>> stored =
      StoredFused(store, snap, profile, *caches.fused);
  if (!stored.ok()) return stored.status();
  std::shared_ptr<const records::FusedValues> fused = *stored;
  if (!fused) {  // no fused tiles under this profile in the version: fuse for this render
    absl::StatusOr<records::FusedValues> on_the_fly = fusion::Fuse(
        snap->records, snap->geometry.size(), snap->geometry.vossel_size_m, profile);
    if (!on_the_fly.ok()) return on_the_fly.status();
    fused = std::make_shared<const records::FusedValues>(std::move(*on_the_fly));
    if (request.interrupt) {  // fusing may have taken long: is the render still wanted?
      if (absl::Status s = request.interrupt(); !s.ok()) return s;
    }
  }
  const store::Snapshot& snapshot = *snap;
  render::ViewBlendInputs blend;
  std::vector<float> lens_values;
  std::shared_ptr<const fusion::RecordValues> lens_reader;  // profile.lens: values as fused
  absl::StatusOr<fusion::RecordWeightsResult> weights;
  absl::StatusOr<std::unique_ptr<SourceTable>> sources;
  const bool detail = request.colour_detail == render::ColourDetail::kSourceImages;
  if (request.eta > 0.0 || detail) {  // §8: the records, their §7 weights, the source origins
    weights = fusion::RecordWeights(snapshot.records, snapshot.geometry.size(),
                                    snapshot.geometry.vossel_size_m, profile);
    if (!weights.ok()) return weights.status();
    sources = Sources(store, snapshot.version);
    if (!sources.ok()) return sources.status();
    blend.source_origin_m = (*sources)->origin_m;
    for (const auto& a : fusion::DenseChannelGains(profile, snapshot.records)) {
      blend.channel_gain.push_back(a);
    }
    if (profile.lens != nullptr) {  // §9: the records' values corrected as fusion reads them
      absl::StatusOr<fusion::RecordValues> values =
          fusion::RecordValues::Of(profile, snapshot.records);
      if (!values.ok()) return values.status();
      lens_reader = std::make_shared<const fusion::RecordValues>(std::move(*values));
      const fusion::RecordValues* reader = lens_reader.get();
      lens_values.resize(snapshot.records.size() * records::kValueChannels);
      tbb::parallel_for(tbb::blocked_range<size_t>(0, snapshot.records.size(), 4096),
                        [&](const tbb::blocked_range<size_t>& r) {
        for (size_t i = r.begin(); i != r.end(); ++i) {
          double v[records::kValueChannels];
          reader->Read(i, v);
          for (int c = 0; c < records::kValueChannels; ++c) {
            lens_values[i * records::kValueChannels + c] = float(v[c]);
          }
        }
      });
      blend.value = &lens_values;
    }
    blend.records = &snapshot.records;
    blend.weight = &weights->weight;
    blend.begin = &weights->begin;
  }
  absl::StatusOr<render::RenderImage> image =
      render::RenderEquirect(snapshot.geometry, *fused, request, &blend);
  if (!image.ok()) return image.status();
  if (detail) {  // §8 with each record's colour read again at the pixel's own point
    if (caches.images == nullptr) {
      return absl::InvalidArgumentError("this engine keeps no source images for colour detail");
    }
    absl::StatusOr<std::vector<render::DetailImage>> images = DetailImages(
        store, **sources, snapshot.records, *weights, *image, caches,
        &image->detail_sources_skipped);
    if (!images.ok()) return images.status();
    blend.images = std::move(*images);
    if (lens_reader != nullptr) {  // §9: each image's samples corrected as its records are
      for (size_t m = 0; m < blend.images.size(); ++m) {
        if (!blend.images[m].image) continue;
        blend.images[m].correct = [lens_reader, m](const float* uv, float* rgb) {
          lens_reader->CorrectImageSample(int32_t(m), uv, rgb);
        };
      }
    }
    if (absl::Status s = render::ApplyColourDetail(snapshot.geometry, request, blend, &*image);
        !s.ok()) {
      return s;
    }
    if (!request.keep_vossel_index) image->vossel_index = {};
  }
  image->version = snapshot.version;
  image->profile = profile.name;
  image->profile_revision = profile.version;
  image->fused_on_the_fly = *stored == nullptr;
  return image;
}

/// Records `image` (a render of `request`) in the catalog and sets its id.
absl::StatusOr<render::RenderImage> Recorded(store::ProjectStore& store,
                                            const render::RenderRequest& request,
                                            render::RenderImage image) {
  absl::StatusOr<int64_t> id = store.RecordRender(RenderRecordOf(request, image));
  if (!id.ok()) return id.status();
  image.render_id = *id;
  return image;
}

}  // namespace

absl::StatusOr<render::RenderImage> RenderQuery(store::ProjectStore& store,
                                               std::shared_ptr<const store::Snapshot> snap,
                                               const fusion::WeightingProfile& profile,
                                               const render::RenderRequest& request,
                                               const RenderCaches& caches) {
  absl::StatusOr<render::RenderImage> image = RenderSnapshot(store, snap, profile, request, caches);
  if (!image.ok()) return image.status();
  return Recorded(store, request, std::move(*image));
}

namespace {

/// What one pass of RenderQueryInTiles composited, and what it read.
struct TiledPass {
  render::RenderImage image;  ///< the composite (its vossel indices kept)
  int groups = 0;
  bool fused_on_the_fly = false;
  int64_t detail_sources = 0, detail_sources_skipped = 0;
};

/// One pass of RenderQueryInTiles: `pass` rendered over the version's tiles nearest the eye
/// first, in groups within `budget_bytes`, each group loaded (with `layers` and, `with_records`,
/// its records), rendered alone and composited; a tile every ray through it has already
/// stopped before is left out (render::RayReach; pixels `pass` does not march count as
/// stopped). Adds the tiles it read to `*read`.
absl::StatusOr<TiledPass> RenderPassInTiles(store::ProjectStore& store, int64_t version,
                                            const store::Manifest& manifest,
                                            const fusion::WeightingProfile& profile,
                                            const render::RenderRequest& pass,
                                            const std::vector<std::string>& layers,
                                            bool with_records, const RenderCaches& caches,
                                            int64_t budget_bytes, std::set<tiles::TileKey>* read) {
  TiledPass out;
  out.image = render::EmptyRender(pass);
  std::vector<double> entry;
  render::RayReach reach(pass);
  auto update_reach = [&] {
    if (pass.start_range_m == nullptr) return reach.Update(entry);
    const std::vector<float>& start = *pass.start_range_m;
    std::vector<double> e(start.size());
    for (size_t p = 0; p < e.size(); ++p) {
      e[p] = !(start[p] < std::numeric_limits<float>::infinity())
                 ? -std::numeric_limits<double>::infinity()
                 : (entry.empty() ? std::numeric_limits<double>::infinity() : entry[p]);
    }
    reach.Update(e);
  };
  update_reach();
  const std::vector<TileBox> order =
      TilesNearestFirst(manifest, pass.pose.o_world, store.settings().tile_vossels,
                        store.settings().vossel_size_m);
  const int fused_layers = 1 + int(layers.size());
  for (size_t next = 0; next < order.size();) {
    std::set<tiles::TileKey> group;
    int64_t held = 0;
    for (; next < order.size(); ++next) {
      const TileBox& tile = order[next];
      if (!reach.MayReach(tile.lo_m, tile.hi_m)) continue;
      const int64_t bytes =
          TileMemoryBytes(manifest.tiles.at(tile.key), with_records, fused_layers);
      if (!group.empty() && held + bytes > budget_bytes) break;
      group.insert(tile.key);
      held += bytes;
    }
    if (group.empty()) break;
    read->insert(group.begin(), group.end());
    if (pass.interrupt) {
      if (absl::Status s = pass.interrupt(); !s.ok()) return s;
    }
    auto part_snap = store.LoadSnapshot(version, layers, with_records, &group);
    if (!part_snap.ok()) return part_snap.status();
    absl::StatusOr<render::RenderImage> part =
        RenderSnapshot(store, *part_snap, profile, pass, caches);
    if (!part.ok()) return part.status();
    if (absl::Status s =
            render::CompositeNearer(pass, (*part_snap)->geometry, *part, &out.image, &entry);
        !s.ok()) {
      return s;
    }
    out.fused_on_the_fly = part->fused_on_the_fly;
    out.detail_sources = std::max(out.detail_sources, part->detail_sources);
    out.detail_sources_skipped = std::max(out.detail_sources_skipped, part->detail_sources_skipped);
    ++out.groups;
    update_reach();
  }
  return out;
}

}  // namespace

absl::StatusOr<render::RenderImage> RenderQueryInTiles(store::ProjectStore& store,
                                                      int64_t version,
                                                      const fusion::WeightingProfile& profile,
                                                      const render::RenderRequest& request,
                                                      const RenderCaches& caches,
                                                      int64_t budget_bytes) {
  absl::StatusOr<store::Manifest> manifest = store.LoadManifest(version);
  if (!manifest.ok()) return manifest.status();
  // What each group loads: the profile's complete fused layer, or the records to fuse from.
  std::vector<std::string> layers;
  bool fuse_here = false;
  if (profile.name != fusion::kDefaultProfileName) {
    const std::string layer = store::FusedLayerName(profile.name, profile.version);
    const std::vector<std::string> complete = store::CompleteProfileLayers(*manifest);
    if (std::find(complete.begin(), complete.end(), layer) != complete.end()) {
      layers.push_back(layer);
    } else {
      fuse_here = true;
    }
  }
  const bool blend = request.eta > 0.0 ||
                     request.colour_detail == render::ColourDetail::kSourceImages;
  std::set<tiles::TileKey> read;
  int groups = 0;

  // The image's own surfaces; with deep output the first pass also keeps the first deep
  // layer's fused colour (layers = 2 there).
  const int L = request.layers;
  render::RenderRequest first = request;
  first.rows_done = {};
  first.keep_vossel_index = true;
  first.layers = std::min(L, 2);
  absl::StatusOr<TiledPass> pass0 = RenderPassInTiles(
      store, version, *manifest, profile, first, layers, fuse_here || blend, caches,
      budget_bytes, &read);
  if (!pass0.ok()) return pass0.status();
  groups += pass0->groups;
  render::RenderImage out = std::move(pass0->image);
  out.vossel_index = {};
  out.fused_on_the_fly = pass0->fused_on_the_fly;
  out.detail_sources = pass0->detail_sources;
  out.detail_sources_skipped = pass0->detail_sources_skipped;
  const size_t n = out.depth_m.size();
  if (L > 1) {  // the deep arrays at L layers, the first from the pass's slot 0 of 2
    const std::vector<float> two_depth = std::move(out.deep_depth_m),
                             two_rgb = std::move(out.deep_rgb),
                             two_alpha = std::move(out.deep_alpha);
    out.layers = L;
    out.layer_count.assign(n, 0);
    out.deep_depth_m.assign(n * size_t(L), std::numeric_limits<float>::infinity());
    out.deep_rgb.assign(3 * n * size_t(L), 0.0f);
    out.deep_alpha.assign(n * size_t(L), 0.0f);
    for (size_t p = 0; p < n; ++p) {
      if (!(out.depth_m[p] < std::numeric_limits<float>::infinity())) continue;
      const size_t q = p * size_t(L);
      out.deep_depth_m[q] = two_depth[2 * p];
      out.deep_alpha[q] = two_alpha[2 * p];
      for (int c = 0; c < 3; ++c) out.deep_rgb[3 * q + c] = two_rgb[3 * 2 * p + c];
      out.layer_count[p] = 1;
    }
  }
  // Deeper layers (§8 deep output), a pass each: layer l marches each pixel from kLayerGapVox
  // beyond layer l-1's hit, as one render's march does, and takes the fused colour C_k.
  std::vector<float> start;
  for (int l = 1; l < L; ++l) {
    start.assign(n, std::numeric_limits<float>::infinity());
    const double gap = render::kLayerGapVox * store.settings().vossel_size_m;
    size_t marched = 0;
    for (size_t p = 0; p < n; ++p) {
      if (out.layer_count[p] < l) continue;
      start[p] = float(double(out.deep_depth_m[p * size_t(L) + size_t(l - 1)]) + gap);
      ++marched;
    }
    if (marched == 0) break;
    render::RenderRequest deeper = first;
    deeper.layers = 1;
    deeper.eta = 0.0;
    deeper.colour_detail = render::ColourDetail::kVossel;
    deeper.start_range_m = &start;
    absl::StatusOr<TiledPass> pass = RenderPassInTiles(
        store, version, *manifest, profile, deeper, layers, fuse_here, caches, budget_bytes,
        &read);
    if (!pass.ok()) return pass.status();
    groups += pass->groups;
    const render::RenderImage& layer = pass->image;
    for (size_t p = 0; p < n; ++p) {
      if (!(layer.depth_m[p] < std::numeric_limits<float>::infinity())) continue;
      const size_t q = p * size_t(L) + size_t(l);
      out.deep_depth_m[q] = layer.depth_m[p];
      out.deep_alpha[q] = layer.alpha[p];
      for (int c = 0; c < 3; ++c) out.deep_rgb[3 * q + c] = layer.rgb[3 * p + c];
      out.layer_count[p] = uint8_t(l + 1);
    }
  }
  out.version = version;
  out.profile = profile.name;
  out.profile_revision = profile.version;
  out.tile_groups = groups;
  out.tiles_read = int64_t(read.size());
  out.tiles_total = int64_t(manifest->tiles.size());
  if (absl::Status s = render::EmitRows(request, out); !s.ok()) return s;
  return Recorded(store, request, std::move(out));
}

store::RenderRecord RenderRecordOf(const render::RenderRequest& request,
                                   const render::RenderImage& image) {
  store::RenderRecord r;
  r.version = image.version;
  r.profile = image.profile;
  r.revision = image.profile_revision;
  r.width_px = image.width_px;
  r.height_px = image.height_px;
  r.pose = request.pose;
  const bool pinhole = request.projection == render::Projection::kPinhole;
  r.projection = pinhole ? "pinhole" : "equirect";
  // The projection as a derived source cites it (DerivedCameraText), then the view term.
  r.camera = absl::StrCat(DerivedCameraText(pinhole, request.pinhole, 0),
                          absl::StrFormat(" eta %.17g", request.eta));
  return r;
}

namespace {

/// The cells k with h·(k − ½) ≤ x < h·(k + ½) that meet a records query's box, [lo, hi];
/// INVALID_ARGUMENT for a bad box or limit.
absl::Status QueryCells(const Eigen::Vector3d& min_m, const Eigen::Vector3d& max_m, double h,
                        int64_t limit, openvdb::Coord* lo, openvdb::Coord* hi) {
  if (!min_m.allFinite() || !max_m.allFinite() || (min_m.array() > max_m.array()).any()) {
    return absl::InvalidArgumentError(
        "a records query needs a finite box with min <= max on every axis (a point: min = max)");
  }
  if (limit <= 0) return absl::InvalidArgumentError("a records query's limit must be positive");
  const Eigen::Vector3d a = (min_m / h).array() + 0.5, b = (max_m / h).array() + 0.5;
  if ((a.array().abs() > 1e9).any() || (b.array().abs() > 1e9).any()) {
    return absl::InvalidArgumentError("a records query's box lies beyond the lattice's reach");
  }
  *lo = openvdb::Coord(int(std::floor(a.x())), int(std::floor(a.y())), int(std::floor(a.z())));
  *hi = openvdb::Coord(int(std::floor(b.x())), int(std::floor(b.y())), int(std::floor(b.z())));
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<RecordsQueryResult> QueryRecords(const store::ProjectStore& store,
                                                const store::Snapshot& snapshot,
                                                const Eigen::Vector3d& min_m,
                                                const Eigen::Vector3d& max_m,
                                                const fusion::WeightingProfile& profile,
                                                int64_t limit) {
  const records::VosselGeometry& g = snapshot.geometry;
  const double h = g.vossel_size_m;
  openvdb::Coord lo, hi;
  if (absl::Status s = QueryCells(min_m, max_m, h, limit, &lo, &hi); !s.ok()) return s;
  RecordsQueryResult out;
  out.profile = profile.name;
  out.revision = profile.version;
  if (g.size() == 0 || !g.index_grid) return out;
  absl::StatusOr<std::unique_ptr<SourceTable>> sources = Sources(store, snapshot.version);
  if (!sources.ok()) return sources.status();
  std::vector<int32_t> vossels;
  const openvdb::CoordBBox box(lo, hi);
  for (auto it = g.index_grid->cbeginValueOn(); it; ++it) {
    openvdb::CoordBBox b;
    it.getBoundingBox(b);
    if (!b.hasOverlap(box)) continue;
    if (it.isVoxelValue()) {
      vossels.push_back(*it);
    } else {
      b.intersect(box);
      for (auto c = b.begin(); c; ++c) {
        int32_t v = -1;
        if (g.index_grid->tree().probeValue(*c, v)) vossels.push_back(v);
      }
    }
  }
  // Tile by tile (key order), then by k: the order RecordsQueryInTiles reads them in.
  const int T = snapshot.tile_vossels;
  std::sort(vossels.begin(), vossels.end(), [&](int32_t a, int32_t b) {
    const openvdb::Coord &ka = g.coord[size_t(a)], &kb = g.coord[size_t(b)];
    const tiles::TileKey ta = tiles::TileOf(ka, T), tb = tiles::TileOf(kb, T);
    if (ta != tb) return ta < tb;
    return ka < kb;
  });
  out.vossels = int64_t(vossels.size());
  // The records of the queried vossels only (whole vossels, until the limit is reached), as a
  // set of their own: a vossel's weights depend on its own records alone (§7), so weighing
  // this set gives what weighing the whole version would, without a pass over every record.
  const records::RecordSet& all = snapshot.records;
  std::vector<size_t> picked;
  std::vector<int32_t> vossel_of;  // local vossel → vossel index
  for (int32_t k : vossels) {
    const auto [first, last] = std::equal_range(all.vossel.begin(), all.vossel.end(), k);
    if (first == last) continue;
    if (int64_t(picked.size()) >= limit) {
      out.truncated = true;
      break;
    }
    for (auto it = first; it != last; ++it) picked.push_back(size_t(it - all.vossel.begin()));
    vossel_of.push_back(k);
  }
  records::RecordSet r = all.Select(picked);
  for (size_t i = 0, local = 0; i < r.size(); ++i) {
    if (i > 0 && r.vossel[i] != all.vossel[picked[i - 1]]) ++local;
    r.vossel[i] = int32_t(local);
  }
  absl::StatusOr<fusion::RecordWeightsResult> weights =
      fusion::RecordWeights(r, vossel_of.size(), h, profile);
  if (!weights.ok()) return weights.status();
  for (size_t local = 0; local < vossel_of.size(); ++local) {
    const int32_t k = vossel_of[local];
    for (size_t i = weights->begin[local]; i < weights->begin[local + 1]; ++i) {
      if (int64_t(out.rows.size()) >= limit) {
        out.truncated = true;
        return out;
      }
      RecordRow row;
      row.vossel = int32_t(local);
      row.coord = g.coord[size_t(k)];
      row.centroid_m = g.centroid_m[size_t(k)].cast<double>();
      row.source = r.scan[i];
      auto src = (*sources)->by_id.find(r.scan[i]);
      if (src != (*sources)->by_id.end()) {
        row.scan_id = src->second.first->id;
        row.scan_name = src->second.first->name;
        row.source_name = src->second.second->name;
      }
      row.modality = records::Modality(r.modality[i]);
      for (int c = 0; c < records::kValueChannels; ++c) row.value[c] = r.value[i * records::kValueChannels + c];
      row.range_m = r.range_m[i];
      row.cos_inc = r.cos_inc[i];
      row.foot_major_m = r.foot_major_m[i];
      row.foot_minor_m = r.foot_minor_m[i];
      row.vis = r.vis[i];
      row.uv_px = {r.uv_px[2 * i], r.uv_px[2 * i + 1]};
      for (int f = 0; f < records::kConfidenceCount; ++f) row.conf[f] = r.conf[i * records::kConfidenceCount + f];
      row.flags = r.flags[i];
      row.batch = r.batch[i];
      row.weight = weights->weight[i];
      out.rows.push_back(std::move(row));
    }
  }
  return out;
}

absl::StatusOr<RecordsQueryResult> QueryRecordsInTiles(const store::ProjectStore& store,
                                                       int64_t version,
                                                       const Eigen::Vector3d& min_m,
                                                       const Eigen::Vector3d& max_m,
                                                       const fusion::WeightingProfile& profile,
                                                       int64_t limit, int64_t budget_bytes) {
  openvdb::Coord lo, hi;
  if (absl::Status s = QueryCells(min_m, max_m, store.settings().vossel_size_m, limit, &lo, &hi);
      !s.ok()) {
    return s;
  }
  absl::StatusOr<store::Manifest> manifest = store.LoadManifest(version);
  if (!manifest.ok()) return manifest.status();
  const std::set<tiles::TileKey> meeting =
      TilesMeeting(*manifest, lo, hi, store.settings().tile_vossels);
  RecordsQueryResult out;
  out.profile = profile.name;
  out.revision = profile.version;
  // Every group is read, so that `vossels` counts the whole box as QueryRecords does; once
  // the rows are full, a group only says whether more would have matched.
  for (const std::set<tiles::TileKey>& group :
       TileGroups(*manifest, /*with_records=*/true, 1, budget_bytes, &meeting)) {
    auto part = store.LoadSnapshot(version, {}, /*with_records=*/true, &group);
    if (!part.ok()) return part.status();
    const int64_t room = limit - int64_t(out.rows.size());
    absl::StatusOr<RecordsQueryResult> found =
        QueryRecords(store, **part, min_m, max_m, profile, std::max<int64_t>(room, 1));
    if (!found.ok()) return found.status();
    out.vossels += found->vossels;
    if (room <= 0) {
      out.truncated = out.truncated || !found->rows.empty();
      continue;
    }
    const int32_t first = out.rows.empty() ? 0 : out.rows.back().vossel + 1;
    for (RecordRow& row : found->rows) {
      row.vossel += first;
      out.rows.push_back(std::move(row));
    }
    out.truncated = out.truncated || found->truncated;
  }
  return out;
}

absl::StatusOr<std::pair<store::VisualReferenceInfo, std::string>> VisualReference(
    const store::ProjectStore& store, const std::vector<store::ScanInfo>& scans,
    const std::string& project, const std::string& scan, const std::string& name) {
  for (const store::ScanInfo& s : scans) {
    if (s.name != scan) continue;
    std::vector<std::string> names;
    for (const store::VisualReferenceInfo& ref : s.visual_references) {
      if (ref.name != name) {
        names.push_back(ref.name);
        continue;
      }
      absl::StatusOr<std::string> bytes = store.ReadBlob(ref.blob_sha256);
      if (!bytes.ok()) return bytes.status();
      return std::make_pair(ref, std::move(*bytes));
    }
    return absl::NotFoundError(absl::StrCat(
        "scan '", scan, "' of project '", project, "' has no visual reference '", name, "'",
        names.empty() ? std::string(" (it has none)")
                      : absl::StrCat(" (it has: ", absl::StrJoin(names, ", "), ")")));
  }
  return absl::NotFoundError(absl::StrCat("project '", project, "' has no scan '", scan, "'"));
}

}  // namespace vasl::flows

// The rebuild flow (flows.h): the whole project recomputed from its raw blobs. The oracle the
// incremental flows are tested against, and the way back from any doubt about derived data.
#include <algorithm>
#include <set>

#include "absl/strings/str_cat.h"
#include "lattice/flows/change.h"
#include "lattice/flows/flows.h"
#include "lattice/flows/tile_budget.h"
#include "lattice/fusion/fuse.h"
#include "lattice/ingest/sample.h"
#include "lattice/ingest/voxelise.h"
#include "lattice/tiles/tile_split.h"

namespace vasl::flows {
namespace {

// What the new version will hold per tile, for tile_budget.h: the new geometry's vossels per
// tile, and HEAD's records of the tile (a rebuild remakes HEAD; a tile HEAD lacks counts none).
store::Manifest EstimateOf(const std::vector<tiles::TileKey>& tile_of,
                           const store::Manifest& head) {
  store::Manifest estimate;
  for (const tiles::TileKey& key : tile_of) ++estimate.tiles[key][store::kLayerGeometry].vossels;
  for (auto& [key, layers] : estimate.tiles) {
    int64_t records = 0;
    if (auto was = head.tiles.find(key); was != head.tiles.end()) {
      if (auto r = was->second.find(store::kLayerRecords); r != was->second.end()) {
        records = r->second.records;
      }
    }
    layers[store::kLayerRecords].records = records;
  }
  return estimate;
}

// Fused layers a version of HEAD's keeps per tile (the default's and each maintained
// profile's).
int FusedLayersOf(const store::Manifest& head) {
  std::set<std::string> layers;
  for (const auto& [key, row] : head.tiles) {
    for (const auto& [layer, entry] : row) {
      if (layer != store::kLayerGeometry && layer != store::kLayerRecords) layers.insert(layer);
    }
  }
  return std::max<int>(1, int(layers.size()));
}

}  // namespace

absl::StatusOr<FlowResult> Rebuild(store::ProjectStore& store, int64_t max_image_pixels,
                                   int64_t max_snapshot_bytes, const StageFn& stage) {
  FlowResult result;
  internal::StageClock clock(result, stage);
  const double h = store.settings().vossel_size_m;
  absl::StatusOr<std::vector<store::ScanInfo>> scans = store.ListScans();
  if (!scans.ok()) return scans.status();
  if (store.head_version() == 0 || scans->empty()) {
    return absl::FailedPreconditionError(
        absl::StrCat("project '", store.name(), "' has no scans to rebuild"));
  }
  const std::vector<internal::SourceRef> sources = internal::SourcesOf(*scans);
  store::Manifest head_manifest;  // the profiles whose layers HEAD keeps stay kept
  if (absl::StatusOr<store::Manifest> m = store.LoadManifest(store.head_version()); m.ok()) {
    head_manifest = std::move(*m);
  } else {
    return m.status();
  }

  // §1: every LiDAR binned and merged in source-id order, one in memory at a time.
  store::Snapshot next;
  next.tile_vossels = store.settings().tile_vossels;
  next.geometry = ingest::EmptyGeometry(h);
  double fraction = 0.05;
  for (const internal::SourceRef& src : sources) {
    if (!src.lidar()) continue;
    if (absl::Status stop = clock.Start(absl::StrCat("voxelise source ", src.info.id), fraction);
        !stop.ok()) {
      return stop;
    }
    absl::StatusOr<ingest::LidarSource> lidar = LoadLidar(store, src.info, src.batch);
    if (!lidar.ok()) return lidar.status();
    absl::StatusOr<ingest::BinnedLidar> binned = ingest::BinLidar(*lidar, h);
    if (!binned.ok()) return binned.status();
    ingest::MergeBinned(next.geometry, *binned);
  }
  if (absl::Status stop = clock.Start("normals", 0.3); !stop.ok()) return stop;
  records::DeriveCentroidAndCovariance(next.geometry);
  ingest::ComputeNormals(next.geometry);

  // The tiles in groups within the budget; one group (the whole version, held and committed
  // as it is) when the version fits.
  const std::vector<tiles::TileKey> tile_of =
      tiles::TilesOfVossels(next.geometry, next.tile_vossels);
  const store::Manifest estimate = EstimateOf(tile_of, head_manifest);
  const int fused_layers = FusedLayersOf(head_manifest);
  std::vector<std::set<tiles::TileKey>> groups;
  if (VersionMemoryBytes(estimate, true, fused_layers) > max_snapshot_bytes) {
    groups = TileGroups(estimate, true, fused_layers, max_snapshot_bytes);
  }
  const bool whole = groups.size() <= 1;
  if (whole) groups = {std::set<tiles::TileKey>(tile_of.begin(), tile_of.end())};
  store::CommitPlan plan;
  plan.made_by = "rebuild";
  plan.replace_all = true;

  // §3-§6, group by group. Every source's records on the group's vossels: in groups, its
  // visibility found on the whole geometry (its depth panorama needs every occluder; its reach
  // raster is taken once) and sampled on the group's vossels alone, the records the whole
  // rebuild makes there; then the group fused and its tiles put.
  const double span = 0.5 / double(groups.size() * sources.size());
  fraction = 0.35;
  std::vector<uint8_t> in_group;
  for (size_t gi = 0; gi < groups.size(); ++gi) {
    const std::set<tiles::TileKey>& group = groups[gi];
    std::string of_group;
    if (!whole) {
      in_group.assign(next.geometry.size(), 0);
      for (size_t k = 0; k < in_group.size(); ++k) in_group[k] = group.count(tile_of[k]) ? 1 : 0;
      of_group = absl::StrCat(" in tile group ", gi + 1, " of ", groups.size(), " (",
                              group.size(), " tiles)");
    }
    for (const internal::SourceRef& src : sources) {
      if (absl::Status stop =
              clock.Start(absl::StrCat("records of source ", src.info.id, of_group), fraction);
          !stop.ok()) {
        return stop;
      }
      fraction += span;
      const bool sized = src.returns() || (src.info.width_px > 0 && src.info.height_px > 0);
      absl::StatusOr<ingest::SourceRecords> recs;
      if (whole || src.derived() || !sized) {
        // Whole; or no depth panorama to find first (a derived source), or its size only in
        // its blob: then its reach is an upper bound (a camera dilates only the rows its tests
        // read).
        recs = internal::StoredSourceRecords(store, src, next.geometry, max_image_pixels,
                                             whole ? nullptr : &in_group, nullptr);
      } else {
        ingest::SourceVisibility visibility =
            internal::StoredVisibility(src, next.geometry, nullptr, nullptr, nullptr);
        for (size_t k = 0; k < in_group.size(); ++k) {
          if (!in_group[k]) visibility.vis[k] = 0.0f;
        }
        recs = internal::StoredSourceRecords(store, src, next.geometry, max_image_pixels,
                                             std::move(visibility));
      }
      if (!recs.ok()) return recs.status();
      next.records.Append(recs->records);
      if (gi == 0 && !src.derived()) next.reach[src.info.id] = std::move(recs->reach);
      if (gi == 0) ++result.sources_computed;
    }
    next.records.SortByVossel();
    if (absl::Status stop = clock.Start(absl::StrCat("fuse", of_group), fraction); !stop.ok()) {
      return stop;
    }
    if (absl::Status s = internal::FuseAll(store, head_manifest, next); !s.ok()) return s;
    if (whole) break;  // committed as it is, every tile's records held
    absl::StatusOr<std::map<tiles::TileKey, std::map<std::string, store::ManifestEntry>>> put =
        store.PutTiles(next, group);
    if (!put.ok()) return put.status();
    plan.put_tiles.insert(put->begin(), put->end());
    next.records = records::RecordSet{};
    next.fused = records::FusedValues{};
    next.profile_fused.clear();
  }
  if (!whole) next.records_partial = true;  // every tile is put; Commit counts from them
  if (absl::Status s = internal::CommitFlow(store, std::move(next), plan, result, clock);
      !s.ok()) {
    return s;
  }
  return result;
}

}  // namespace vasl::flows

// The scan deletion flow (flows.h): a new version without one scan. The vossel sums of the
// tiles its LiDAR touched are recomputed from the other scans' blobs (in source-id order, as a
// rebuild adds them), normals where a neighbourhood changed, and older sources are revisited
// where the removed geometry changes what they see (change.h).
#include <algorithm>

#include "absl/strings/str_cat.h"
#include "lattice/flows/change.h"
#include "lattice/flows/flows.h"
#include "lattice/records/record_grid.h"
#include "lattice/ingest/voxelise.h"
#include "lattice/tiles/tile_split.h"

namespace vasl::flows {

absl::StatusOr<FlowResult> DeleteScan(store::ProjectStore& store, const store::Snapshot& head,
                                      const std::string& scan_name, int64_t max_image_pixels,
                                      const StageFn& stage, SourceImageCache* images) {
  FlowResult result;
  internal::StageClock clock(result, stage);
  const double h = store.settings().vossel_size_m;
  const int T = store.settings().tile_vossels;
  absl::StatusOr<std::vector<store::ScanInfo>> scans = store.ListScans(head.version);
  if (!scans.ok()) return scans.status();
  if (head.version == 0) scans->clear();
  auto doomed = std::find_if(scans->begin(), scans->end(),
                             [&](const store::ScanInfo& s) { return s.name == scan_name; });
  if (doomed == scans->end()) {
    return absl::NotFoundError(
        absl::StrCat("project '", store.name(), "' has no scan '", scan_name, "'"));
  }
  internal::Change change;
  std::set<tiles::TileKey> emptied;  // tiles whose sums are recomputed
  for (const store::SourceInfo& src : doomed->sources) {
    change.dropped_sources.insert(src.id);
    if (src.modality != records::Modality::kLidar) continue;
    absl::StatusOr<std::set<tiles::TileKey>> t = store.SourceTiles(src.id);
    if (!t.ok()) return t.status();
    emptied.insert(t->begin(), t->end());
  }
  store::ScanInfo gone = *doomed;
  scans->erase(doomed);
  const std::vector<internal::SourceRef> remaining = internal::SourcesOf(*scans);

  // §1: the vossels outside the emptied tiles as they were; those inside rebuilt from zero by
  // every remaining LiDAR with returns there, in source-id order.
  if (absl::Status stop = clock.Start("voxelise", 0.1); !stop.ok()) return stop;
  const records::VosselGeometry& old = head.geometry;
  records::VosselGeometry& g = change.geometry;
  g.vossel_size_m = h;
  std::vector<int32_t> kept_old;  // old index of each kept vossel, in order
  for (size_t v = 0; v < old.size(); ++v) {
    if (emptied.count(tiles::TileOf(old.coord[v], T))) continue;
    kept_old.push_back(int32_t(v));
    g.coord.push_back(old.coord[v]);
    g.point_count.push_back(old.point_count[v]);
    g.sums.push_back(old.sums[v]);
    g.centroid_m.push_back(old.centroid_m[v]);
    g.normal.push_back(old.normal[v]);
    g.covariance_m2.push_back(old.covariance_m2[v]);
    g.frame.push_back(old.frame[v]);
  }
  records::CanonicalizeVosselOrder(g);
  for (const internal::SourceRef& src : remaining) {
    if (!src.lidar()) continue;
    absl::StatusOr<std::set<tiles::TileKey>> t = store.SourceTiles(src.info.id);
    if (!t.ok()) return t.status();
    if (std::none_of(t->begin(), t->end(), [&](const tiles::TileKey& k) { return emptied.count(k) > 0; })) {
      continue;
    }
    if (absl::Status stop = clock.Start(absl::StrCat("re-voxelise source ", src.info.id), 0.2);
        !stop.ok()) {
      return stop;
    }
    absl::StatusOr<ingest::LidarSource> lidar = LoadLidar(store, src.info, src.batch);
    if (!lidar.ok()) return lidar.status();
    absl::StatusOr<ingest::BinnedLidar> binned = ingest::BinLidar(*lidar, h);
    if (!binned.ok()) return binned.status();
    ingest::BinnedLidar inside;
    for (size_t i = 0; i < binned->size(); ++i) {
      if (!emptied.count(tiles::TileOf(binned->coord[i], T))) continue;
      inside.coord.push_back(binned->coord[i]);
      inside.count.push_back(binned->count[i]);
      inside.sums.push_back(binned->sums[i]);
    }
    ingest::MergeBinned(g, inside);
  }
  records::DeriveCentroidAndCovariance(g);

  // Old → new numbering by coordinate (vossels of emptied tiles may be gone).
  change.old_to_new.assign(old.size(), -1);
  {
    auto acc = g.index_grid->getConstAccessor();
    for (size_t v = 0; v < old.size(); ++v) {
      int32_t n;
      if (acc.probeValue(old.coord[v], n)) change.old_to_new[v] = n;
    }
  }
  // Normals of every vossel whose neighbourhood reaches into an emptied tile.
  if (absl::Status stop = clock.Start("normals", 0.35); !stop.ok()) return stop;
  std::vector<uint8_t> renormal(g.size(), 0);
  for (size_t v = 0; v < g.size(); ++v) {
    const openvdb::Coord c = g.coord[v];
    for (int corner = 0; corner < 8 && !renormal[v]; ++corner) {
      const openvdb::Coord n = c.offsetBy((corner & 1) ? 1 : -1, (corner & 2) ? 1 : -1,
                                          (corner & 4) ? 1 : -1);
      if (emptied.count(tiles::TileOf(n, T))) renormal[v] = 1;
    }
  }
  ingest::ComputeNormals(g, &renormal);

  store::CommitPlan plan;
  plan.made_by = absl::StrCat("delete scan ", gone.name);
  plan.delete_scan = gone.name;
  absl::StatusOr<store::Snapshot> next = internal::Propagate(
      store, head, std::move(change), remaining, max_image_pixels, images, plan, result, clock);
  if (!next.ok()) return next.status();
  if (absl::Status s = internal::CommitFlow(store, std::move(*next), plan, result, clock); !s.ok()) {
    return s;
  }
  return result;
}

}  // namespace vasl::flows

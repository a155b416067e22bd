// The incremental ingest flow (flows.h): a scan's own points merged into the lattice, normals
// recomputed where a neighbourhood changed, records of its own sources, and older sources
// revisited only where the new geometry reaches them (change.h).
#include "absl/strings/str_cat.h"
#include "lattice/flows/change.h"
#include "lattice/flows/flows.h"
#include "lattice/ingest/voxelise.h"
#include "lattice/tiles/tile_split.h"

namespace vasl::flows {

absl::StatusOr<FlowResult> IngestScan(store::ProjectStore& store, const store::Snapshot& head,
                                      const store::ScanInfo& info, const ingest::LidarData& lidar,
                                      std::vector<ingest::LinearImage> images,
                                      int64_t max_image_pixels, const StageFn& stage) {
  FlowResult result;
  internal::StageClock clock(result, stage);
  const double h = store.settings().vossel_size_m;
  const int T = store.settings().tile_vossels;

  // The scan's sources as the stages consume them.
  internal::Change change;
  size_t next_image = 0;
  for (const store::SourceInfo& src : info.sources) {
    if (src.modality == records::Modality::kLidar) {
      ingest::LidarSource l = LidarOf(src, info.batch);
      l.xyz_sensor_m = lidar.xyz_sensor_m;
      l.intensity = lidar.intensity;
      change.new_sources.lidars.push_back(std::move(l));
    } else {
      if (next_image >= images.size()) {
        return absl::InternalError("IngestScan: fewer decoded images than camera sources");
      }
      ingest::CameraSource cam = CameraOf(src, info.batch);
      cam.image = std::move(images[next_image++]);
      change.new_sources.cameras.push_back(std::move(cam));
    }
  }
  if (change.new_sources.lidars.size() != 1) {
    return absl::InternalError("IngestScan: a scan has exactly one LiDAR source");
  }

  // §1: bin the scan's own returns and merge them (exact sums), then derive.
  clock.Start("voxelise", 0.2);
  absl::StatusOr<ingest::BinnedLidar> binned = ingest::BinLidar(change.new_sources.lidars[0], h);
  if (!binned.ok()) return binned.status();
  change.geometry = head.geometry.size() == 0 ? ingest::EmptyGeometry(h) : head.geometry;
  const ingest::MergeResult merged = ingest::MergeBinned(change.geometry, *binned);
  ingest::DeriveCentroidAndCovariance(change.geometry);
  change.old_to_new = merged.old_to_new;

  // Normals where a neighbourhood changed: the touched vossels and their 26 neighbours.
  clock.Start("normals", 0.35);
  std::vector<uint8_t> renormal(change.geometry.size(), 0);
  {
    auto acc = change.geometry.index_grid->getConstAccessor();
    for (size_t v = 0; v < merged.touched.size(); ++v) {
      if (!merged.touched[v]) continue;
      const openvdb::Coord c = change.geometry.coord[v];
      for (int dx = -1; dx <= 1; ++dx)
        for (int dy = -1; dy <= 1; ++dy)
          for (int dz = -1; dz <= 1; ++dz) {
            int32_t n;
            if (acc.probeValue(c.offsetBy(dx, dy, dz), n)) renormal[size_t(n)] = 1;
          }
    }
  }
  ingest::ComputeNormals(change.geometry, &renormal);

  absl::StatusOr<std::vector<store::ScanInfo>> scans = store.ListScans(head.version);
  if (!scans.ok()) return scans.status();
  if (head.version == 0) scans->clear();
  store::CommitPlan plan;
  plan.made_by = absl::StrCat("ingest scan ", info.name);
  plan.add_scan = info;
  std::set<tiles::TileKey>& returns = plan.source_tiles[change.new_sources.lidars[0].id];
  for (const openvdb::Coord& c : binned->coord) returns.insert(tiles::TileOf(c, T));

  absl::StatusOr<store::Snapshot> next =
      internal::Propagate(store, head, std::move(change), internal::SourcesOf(*scans),
                          max_image_pixels, plan, result, clock);
  if (!next.ok()) return next.status();
  if (absl::Status s = internal::CommitFlow(store, std::move(*next), plan, result, clock); !s.ok()) {
    return s;
  }
  return result;
}

}  // namespace vasl::flows

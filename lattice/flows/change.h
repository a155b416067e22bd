/// @file change.h
/// @brief Internal to the flows: propagating a change of geometry to the records it reaches
///        (VASL-MODEL §5). Shared by ingest (geometry grows) and delete (geometry shrinks).
/// @details Which (older source m, tile t) pairs must be recomputed, and why that is exact:
///          a record of m on vossel k depends on k's geometry and on m's depth panorama D_m at
///          the pixels k's visibility test reads. Both are evaluated on k's record frame
///          (records::VosselFrame), not on the surface of all scans. D_m is a min over splats of
///          every vossel; a splat changes only for a vossel whose frame changed (or that
///          appeared or vanished): the "changed" tiles C. Appending a scan leaves the frames of
///          the vossels it re-observes as they were, so C is the new vossels and the
///          neighbours whose frame normal they change. Let cap_m(t) be the directions in which
///          tile t (grown by 2h for splat and patch extents) appears from m, widened by m's
///          angular margin (pixel pitch, beam divergence, camera dilation).
///          1. A block c of changed vossels that m's reach raster says m cannot reach (every
///             cell of cap_m(c) nearer than both c's near distance less 2h and every changed
///             vossel's range less h and its visibility tolerance τ_k) changes nothing: its old
///             and new splats lie behind D_m everywhere they fall, and none of its changed
///             vossels is visible before or after. cap_m(c) is the cap of the box of c's
///             changed cells, not of the whole block.
///          2. A reachable changed block c can alter D_m only inside cap_m(c), and only at
///             depths ≥ near(c) − 2h; so it can alter the visibility of tile t only when
///             cap_m(t) meets cap_m(c) and far(t) + 4h ≥ near(c).
///          The rules are applied to blocks of 16³ vossels (finer than tiles): the blocks of 2
///          (c itself included) are m's revisited blocks; a LiDAR's are kept to the tiles where
///          it has returns (it records nothing elsewhere).
///          3. Within them, vossel by vossel: D_m before and after are min(D_rest, S_old) and
///             min(D_rest, S_new), S the changed vossels' splats; an unchanged vossel k's test
///             at a pixel changes only where min(S_old, S_new) lies below its threshold there.
///             Only the changed vossels and those with such a sample are recomputed
///             (RevisitScope).
///          Everything else keeps its records bit for bit. The recomputation renders D_m from
///          every block whose splats can fall where the recomputed tests read at a depth they
///          compare (blocks wholly behind those tests are left out: see ScopeOf), so its records
///          equal a rebuild's and its new reach raster bounds a rebuild's from above.
#pragma once

#include <chrono>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include "lattice/flows/flows.h"
#include "lattice/ingest/sample.h"
#include "lattice/ingest/sources.h"
#include "lattice/store/project_store.h"
#include "lattice/tiles/tiling.h"

namespace vasl::flows::internal {

/// Times the stages of a flow into FlowResult::stage_seconds and reports each start.
class StageClock {
 public:
  StageClock(FlowResult& result, const StageFn& stage) : result_(result), stage_(stage) {}
  /// Closes the running stage (if any) and starts `name` at `fraction` of the flow; the
  /// caller's answer (StageFn): a flow returns at once with a status that is not OK.
  [[nodiscard]] absl::Status Start(const std::string& name, double fraction);
  /// Closes the running stage.
  void Finish();

 private:
  using Clock = std::chrono::steady_clock;
  FlowResult& result_;
  const StageFn& stage_;
  std::string running_;
  Clock::time_point t0_;
};

/// A source of the project as the catalog holds it, with its scan's batch.
struct SourceRef {
  store::SourceInfo info;
  int32_t batch = 0;
  bool lidar() const { return info.modality == records::Modality::kLidar; }
  /// The colour of a LiDAR's returns (IsPointColour): its records, depth panorama and reach
  /// are a LiDAR's, its samples colours.
  bool point_colour() const { return IsPointColour(info); }
  /// Records made from a LiDAR's returns (intensity or colour): only where it has returns.
  bool returns() const { return lidar() || point_colour(); }
  /// An image sent back as derived data (§10): no geometry, no depth panorama, no reach.
  bool derived() const { return info.modality == records::Modality::kDerived; }
};
/// Every source of `scans`, in source-id order.
std::vector<SourceRef> SourcesOf(const std::vector<store::ScanInfo>& scans);

/// A block of (at most) 16³ vossels holding changed vossels: the unit of the reach test, finer
/// than a tile so that a change at one end of a tile is not taken as seen by every sensor that
/// sees the tile's other end.
struct ChangedBlock {
  tiles::TileKey key;                       ///< the block's key (TileOf with BlockVossels(T))
  tiles::TileKey tile;                      ///< the tile the block lies in
  tiles::Box box;                           ///< the bounding box of its changed cells
  std::vector<Eigen::Vector3d> centroid_m;  ///< changed vossels' frames, old and new state
  std::vector<Eigen::Vector3d> normal;      ///< their normals (zero: none)
};

/// Edge of a block in vossels for tiles of edge T: 16, or T when smaller.
inline int BlockVossels(int T) { return T < 16 ? T : 16; }

/// The vossels a geometry change touched, one by one (ChangedBlocks).
struct ChangedVossels {
  std::vector<uint8_t> changed_new;  ///< per new vossel: appeared, or its record frame changed
  std::vector<int32_t> new_to_old;   ///< per new vossel: the old vossel it was, or −1 (appeared)
  /// The old vossels that vanished or whose record frame changed, in their old state, as depth
  /// panoramas splat them (each one's frame centroid and normal as its surface).
  records::VosselGeometry old_splats;
};

/// Blocks of the vossels that appeared, vanished or whose record frame changed between `old`
/// and `now` (`old_to_new` maps old vossels to new ones, −1: gone), in their frames' centroids
/// and normals; when either geometry has no frames, the surface stands in for them. Adds to
/// `surface_tiles` every tile where a vossel appeared, vanished or changed its surface or frame
/// (the geometry files a commit rewrites), and fills `vossels` when given.
std::vector<ChangedBlock> ChangedBlocks(const records::VosselGeometry& old,
                                        const records::VosselGeometry& now,
                                        const std::vector<int32_t>& old_to_new, int T,
                                        std::set<tiles::TileKey>* surface_tiles,
                                        ChangedVossels* vossels = nullptr);

/// The blocks of `all` (block keys, edge B vossels) whose records from `source` may change when
/// the `changed` blocks change (see @details, applied per block: rule 1 with the depth margin
/// of the block's own changed vossels' visibility tolerances), given the source's reach raster
/// (nullptr: unknown, every changed block counts as reachable). `h` vossel edge.
std::set<tiles::TileKey> AffectedBlocks(const SourceRef& source, const tiles::ReachRaster* reach,
                                        const std::vector<ChangedBlock>& changed,
                                        const std::set<tiles::TileKey>& all, int B, double h);

/// What a revisit of a source recomputes, and what it renders to do so (rule 3 of @details).
/// Of the vossels of its revisited blocks, the records recomputed are those of the changed
/// vossels and of the vossels with a visibility test sample where a changed splat, old or new,
/// lies nearer than the sample's threshold (found on a depth panorama of the changed splats
/// alone, dilated as the source's): every other test reads the depth of the unchanged vossels
/// before and after, so those records stay bit for bit. The depth panorama is then splatted
/// exactly on `cells` (the reach cells the recomputed tests read, a camera's dilation included,
/// and those an old splat the source saw left, whose reach the revisit recomputes; none: the
/// change alters nothing of the source) from the `context` blocks:
/// those whose splats can fall in such a cell nearer than the farthest test or old splat
/// there. Deeper splats cannot change a test D(p) ≥ r − τ with r below them, so the records
/// recomputed are a rebuild's, and the fresh reach in `cells` bounds a rebuild's from above.
struct RevisitScope {
  std::vector<uint8_t> only;     ///< per vossel of the new geometry: its records are recomputed
  std::vector<uint8_t> context;  ///< per vossel: splatted into the depth panorama
  std::vector<uint8_t> cells;    ///< per reach cell of the depth panorama: 2 splatted exactly
};
/// Every splat a change touched, as the depth panoramas splat them (each one's frame centroid
/// and normal as its surface): the old state of the vossels that vanished or were reframed
/// (the first `before`), then the new state of those that appeared or were reframed.
struct ChangedSplats {
  records::VosselGeometry splats;
  size_t before = 0;
};
/// The scope of a revisit of `source` whose revisited blocks hold the `candidates` vossels of
/// `g` (`changed_new` as ChangedVossels'); `blocks` numbers the blocks of `g` (edge B) and
/// `block_of` gives each vossel's number; `reach`: the source's reach raster before the change
/// (nullptr: unknown), which says which old splats lay behind the old depth everywhere.
RevisitScope ScopeOf(const SourceRef& source, const records::VosselGeometry& g,
                     const std::vector<uint8_t>& candidates,
                     const std::vector<uint8_t>& changed_new, const ChangedSplats& changes,
                     const std::vector<tiles::TileKey>& blocks,
                     const std::vector<int32_t>& block_of, int B,
                     const tiles::ReachRaster* reach);

/// The records (and reach raster) of a stored source on `geometry`, its points or image read
/// back from its blob; `only` and `context` as ingest::LidarRecords / CameraRecords.
absl::StatusOr<ingest::SourceRecords> StoredSourceRecords(
    const store::ProjectStore& store, const SourceRef& source,
    const records::VosselGeometry& geometry, int64_t max_image_pixels,
    const std::vector<uint8_t>* only = nullptr, const std::vector<uint8_t>* context = nullptr);

/// The visibility of a stored source on `geometry` (ingest::LidarVisibility, CameraVisibility
/// with the image size the catalog holds), found without reading its blob; its depth panorama
/// splatted only on the reach cells `read_cells` flags when given (a revisit's scope).
ingest::SourceVisibility StoredVisibility(const SourceRef& source,
                                          const records::VosselGeometry& geometry,
                                          const std::vector<uint8_t>* only,
                                          const std::vector<uint8_t>* context,
                                          const std::vector<uint8_t>* read_cells);
/// The records of a stored source whose visibility is known, from its blob (not derived); a
/// camera's image through `images` when given (LoadedCamera).
absl::StatusOr<ingest::SourceRecords> StoredSourceRecords(const store::ProjectStore& store,
                                                          const SourceRef& source,
                                                          const records::VosselGeometry& geometry,
                                                          int64_t max_image_pixels,
                                                          ingest::SourceVisibility visibility,
                                                          SourceImageCache* images = nullptr);

/// The records of `source` on the `only` vossels of `geometry` after a change, refreshed from
/// its records there before it (`before`, renumbered to `geometry`'s vossels) where that is
/// exact, given its visibility after the change: a record keeps its sample and takes the new
/// V (none where V = 0), and on a vossel whose record frame changed a LiDAR's (or its point
/// colour's) record takes the frame's range, incidence, footprint and uv (ingest::ReturnTermsOf:
/// the mean of its returns does not depend on the frame). nullopt when some record needs the
/// source's points or pixels: a camera's on a changed frame, or a vossel seen now that the
/// source did not record before, unless it is a LiDAR's and the vossel appeared after it (its
/// returns made every vossel they fell in) or the vossel was seen before too, so that it was
/// left unrecorded for good: an unchanged vossel whose samples the changed vossels' old splats
/// lie behind, or a LiDAR's vossel whose frame changed and one of whose old samples lay nearer
/// than min(its depth now, those old splats). `old_geometry`: the geometry before the change.
std::optional<records::RecordSet> RefreshedRecords(const SourceRef& source,
                                                   records::RecordSet before,
                                                   const records::VosselGeometry& old_geometry,
                                                   const records::VosselGeometry& geometry,
                                                   const ChangedVossels& changed,
                                                   const std::vector<uint8_t>& only,
                                                   const ingest::SourceVisibility& visibility);

/// A geometry change ready to propagate.
struct Change {
  records::VosselGeometry geometry;        ///< the new geometry, final (sums, centroids, normals)
  std::vector<int32_t> old_to_new;         ///< per vossel of the old geometry: new index or −1
  std::set<int32_t> dropped_sources;       ///< sources whose records and reach leave the project
  ingest::SourceSet new_sources;           ///< sources computed on every tile (a new scan's)
};

/// Propagates `change` from `old`: finds the changed tiles (vossels that appeared, vanished or
/// whose count, centroid or normal changed), computes the new sources, carries every
/// unaffected record over, recomputes the affected (older source, tile) pairs from their
/// blobs, fuses (§7, default profile) and fills `plan` with what changed. `old_sources` are
/// the sources of `old` that stay. With `old` loaded without records (a change within the
/// engine's memory budget) it reads the records of the tiles it rewrites only, and the new
/// snapshot holds those (Snapshot::records_partial). Revisits read cameras through `images`
/// (may be null: each decoded for the revisit alone). Returns the new snapshot (version not
/// yet set).
absl::StatusOr<store::Snapshot> Propagate(const store::ProjectStore& store,
                                          const store::Snapshot& old, Change change,
                                          const std::vector<SourceRef>& old_sources,
                                          int64_t max_image_pixels, SourceImageCache* images,
                                          store::CommitPlan& plan,
                                          FlowResult& result, StageClock& clock);

/// §7 fusion of `next`'s records under the default profile and under every profile whose
/// fused layers the project keeps (reweight::MaintainedProfiles of `head`): fills next.fused
/// and next.profile_fused, so that the tiles a commit rewrites keep every profile's layer.
absl::Status FuseAll(const store::ProjectStore& store, const store::Manifest& head,
                     store::Snapshot& next);

/// Commits `next` under `plan`, fills the result's version, snapshot and write figures.
absl::Status CommitFlow(store::ProjectStore& store, store::Snapshot next,
                        const store::CommitPlan& plan, FlowResult& result, StageClock& clock);

}  // namespace vasl::flows::internal

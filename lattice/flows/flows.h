/// @file flows.h
/// @brief The flows that make new versions of a tiled project (ARCHITECTURE.md "The main
///        flows"): incremental ingest, scan deletion and rebuild. Each lives in its own file
///        (ingest_flow.cc, delete_flow.cc, rebuild_flow.cc) over the shared change propagation
///        of change.h; the engine facade validates input, serialises writers and calls them.
/// @details Rebuild is the oracle: it recomputes a whole project from its raw blobs. Ingest and
///          delete change only what the change reaches (VASL-MODEL §5): the tiles whose vossels
///          the scan's points touch, the vossels whose normal moved, and, for older sources, the
///          (source, tile) pairs whose depth panorama the changed geometry can alter, found from
///          each source's stored reach raster. Both give the same records, record by record, as
///          a rebuild of the same scans (tests/flows/incremental_test.cc).
#pragma once

#include <cstdint>
#include <filesystem>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "lattice/ingest/artefacts.h"
#include "lattice/ingest/scan_input.h"
#include "lattice/ingest/sources.h"
#include "lattice/fusion/profile.h"
#include "lattice/render/render.h"
#include "lattice/store/project_store.h"

namespace vasl::flows {

/// Called as each stage of a flow starts: its name and the fraction of the flow done. A status
/// other than OK stops the flow there with that status (ingest::ProgressFn), before its commit.
using StageFn = std::function<absl::Status(const std::string& stage, double fraction)>;

/// What a flow committed and what it cost.
struct FlowResult {
  std::shared_ptr<const store::Snapshot> snapshot;  ///< the committed version, in memory
  int64_t version = 0;
  std::vector<std::pair<std::string, double>> stage_seconds;  ///< per stage, in order
  int64_t sources_computed = 0;  ///< sources whose records were computed on every tile they see
  int64_t sources_revisited = 0;  ///< older sources recomputed on some tiles
  int64_t pairs_revisited = 0;    ///< (older source, tile) pairs with records recomputed
  int64_t blocks_revisited = 0;   ///< (older source, 16³-vossel block) pairs recomputed
  int64_t vossels_revisited = 0;  ///< (older source, vossel) pairs of those blocks recomputed
  int64_t vossels_in_blocks = 0;  ///< (older source, vossel) pairs those blocks hold
  /// Of the sources revisited, those whose records were refreshed from their records before
  /// the change (visibility, and a LiDAR's geometric terms) without reading their blob.
  int64_t sources_refreshed = 0;
  int64_t tiles_changed = 0;      ///< tiles whose objects the commit wrote
  int64_t bytes_written = 0;      ///< bytes of objects the commit wrote
  /// Records the change computed (its new sources' and its revisited pairs'), and every record
  /// of the tiles whose records the commit rewrote: the rest of those were carried over
  /// unchanged (what record segments per batch would not rewrite; README "Storage").
  int64_t records_computed = 0;
  int64_t records_rewritten = 0;
  store::CommitTimes commit_times;  ///< where its commit's time went (ProjectStore)
  int64_t pixels_back_projected = 0;  ///< back-projection: pixels that became derived records
  int64_t pixels_outside = 0;         ///< back-projection: pixels whose point is in no vossel
  int64_t pixels_invalid = 0;         ///< back-projection: surface pixels with a non-finite colour
  /// Ingest: §2.3 calibration health of each camera of the scan (by name) against its LiDAR.
  std::vector<std::pair<std::string, records::CalibrationHealth>> calibration;
};

/// A source's catalog fields (id, batch, pose, divergence or angular resolution, modality, a
/// camera's projection) as the stages take them, without its points or image. A camera text
/// that does not parse leaves it equirect; StoredCamera's loader refuses it (DATA_LOSS).
ingest::LidarSource LidarOf(const store::SourceInfo& source, int32_t batch);
ingest::CameraSource CameraOf(const store::SourceInfo& source, int32_t batch);

/// A derived source's camera text (SourceInfo::camera) and back: "equirect", "pinhole fx fy
/// cx cy k1 k2 k3 p1 p2" or "fisheye fx fy cx cy k1 k2 k3 k4[ field RAD]" (geometry::Lens::
/// kFisheye, its field of view when it has one), then
/// " render ID" when it cites a render. A camera's is empty (an equirect panorama) or the same
/// pinhole or fisheye text (a photo).
std::string DerivedCameraText(bool pinhole, const geometry::PinholeIntrinsics& k, int64_t render_id);
/// The projection a camera text names: nullopt for an equirect one ("" or "equirect"), the
/// intrinsics (width and height 0) for "pinhole …" and "fisheye …". DATA_LOSS for any other
/// text.
absl::StatusOr<std::optional<geometry::PinholeIntrinsics>> ProjectionOfCameraText(
    const std::string& camera_text);
/// A camera's text for an equirect panorama of part of the sphere: "equirect window LEFT TOP"
/// (the sphere's size is the source's width and height; ProjectionOfCameraText reads it as
/// equirect) and back: nullopt for any other text, DATA_LOSS for a bad window text.
std::string SphereCameraText(const ingest::SphereWindow& window);
absl::StatusOr<std::optional<ingest::SphereWindow>> SphereOfCameraText(
    const store::SourceInfo& source);
/// A cylindrical panorama's camera text: "equirect cylinder PITCH PIXEL_HEIGHT RADIUS
/// PRINCIPAL_Y" (ingest::CylinderImage; the sphere it is resampled into is the source's width
/// and height) and back: nullopt for any other text, DATA_LOSS for a bad cylinder text.
std::string CylinderCameraText(const ingest::CylinderImage& cylinder);
absl::StatusOr<std::optional<ingest::CylinderImage>> CylinderOfCameraText(
    const std::string& camera_text);
/// True for a camera whose image is part of its sphere (a window or a cylinder).
bool PartOfTheSphere(const store::SourceInfo& source);
/// A stored derived source whose image is decoded from its blob on demand. DATA_LOSS for a
/// camera text or image it cannot read.
absl::StatusOr<ingest::DerivedSource> LoadDerived(const store::ProjectStore& store,
                                                  const store::SourceInfo& source, int32_t batch,
                                                  int64_t max_image_pixels);

/// The LiDAR of a stored source, from its blob (packed float32 x, y, z, intensity).
/// DATA_LOSS when the blob is damaged.
absl::StatusOr<ingest::LidarSource> LoadLidar(const store::ProjectStore& store,
                                              const store::SourceInfo& source, int32_t batch);
/// A stored LiDAR with its gap fill at the project's vossel size computed, read from `images`
/// when it keeps it and kept there after a load (as LoadedCamera keeps cameras); with no cache,
/// LoadLidar's, its gap fill computed.
class SourceImageCache;
absl::StatusOr<std::shared_ptr<const ingest::LidarSource>> LoadedLidar(
    const store::ProjectStore& store, const store::SourceInfo& source, int32_t batch,
    SourceImageCache* images);
/// A point-colour source's camera text (SourceInfo::camera): "points SHA", SHA the blob of the
/// scan's LiDAR points the colours belong to (its own blob holds float32 r, g, b per point, in
/// the same order, linear).
std::string PointColourCameraText(const std::string& lidar_blob_sha256);
/// True for a source whose camera text names a LiDAR's points (a point-colour source).
bool IsPointColour(const store::SourceInfo& source);
/// The LiDAR points of a stored point-colour source with their colours, as a LidarSource whose
/// `colour_id` is the source's id. DATA_LOSS when a blob is damaged or the counts disagree.
absl::StatusOr<ingest::LidarSource> LoadPointColour(const store::ProjectStore& store,
                                                    const store::SourceInfo& source,
                                                    int32_t batch);
/// A stored camera with its image decoded and its artefact maps found, read from `images`
/// when it keeps them and kept there after a decode (revisits of successive ingests mostly
/// read the same cameras); with no cache, StoredCamera's (decoded on demand). An image kept as
/// floats is shared with the camera (CameraSource::kept_image), its §9 channel shift corrected
/// once; one kept as its 8-bit codes is the camera's `load` (unpacked when its records are
/// sampled, and corrected on the rows they read).
class SourceImageCache;
absl::StatusOr<ingest::CameraSource> LoadedCamera(const store::ProjectStore& store,
                                                  const store::SourceInfo& source,
                                                  int32_t batch, int64_t max_image_pixels,
                                                  SourceImageCache* images);
/// Hands the image a scan's camera `cam` (of catalog source `source`) holds decoded to the
/// cameras that read it next: as LoadedCamera would keep it in `images` (artefacts found, channel
/// shift corrected) and on `cam` as its kept image, so that the next ingest's revisit of the
/// camera finds it decoded. Nothing when `cam` holds no decoded image or there is no cache.
/// `decode_seconds`: what its decode took (with the maps' and the correction's, its worth there).
void KeepDecodedCamera(const store::SourceInfo& source, int64_t max_image_pixels,
                       SourceImageCache* images, ingest::CameraSource& cam,
                       double decode_seconds = 0.0);
/// A stored camera whose image is decoded from its blob on demand (`load`), its mask applied
/// (ingest::ApplyMask) when it has one and placed in its sphere when it spans part of it
/// (ingest::PlaceInSphere; a cylindrical one resampled first, ingest::CylinderToSphere).
ingest::CameraSource StoredCamera(const store::ProjectStore& store,
                                  const store::SourceInfo& source, int32_t batch,
                                  int64_t max_image_pixels);
/// What a stored camera's decoded image depends on, as a cache key: its blob, its mask's, and
/// where it lies in its sphere.
std::string DecodedImageKey(const store::SourceInfo& source);
/// The bytes a stored camera's decoded image takes, as far as the catalog tells: 3 floats a
/// pixel, 4 with a mask or as part of the sphere (a window or a cylinder: its coverage; an
/// image's own alpha is known only once decoded).
int64_t DecodedImageBytes(const store::SourceInfo& source);

/// FAILED_PRECONDITION: a camera-only scan (images, no points) sent to a project without
/// geometry, which it would have nothing to colour on.
absl::Status CameraOnlyWithoutGeometry(const std::string& project, const std::string& scan);

/// Stores a validated scan's raw inputs as content-addressed blobs (its LiDAR points packed as
/// little-endian float32 x, y, z, intensity; per-point colour, when given, as float32 r, g, b;
/// its encoded images) and returns its catalog description: sources with fresh ids (LiDAR
/// first when it has points, then its point colour when given, then cameras in order; a
/// pinhole camera's intrinsics in its camera text), a fresh batch.
/// `images` are its panoramas' headers (for their sizes, ingest::ValidateScan).
absl::StatusOr<store::ScanInfo> StoreScanBlobs(store::ProjectStore& store, const ingest::ScanInput& scan,
                                               const std::vector<ingest::ImageHeader>& images);

/// Incremental ingest of one validated scan (`scan`) whose blobs are stored: `info` carries
/// its sources (ids, poses, blob hashes, sizes). Each panorama is decoded as its camera's
/// records are made and freed after, so an ingest holds one decoded panorama at a time.
/// `head` is the project's HEAD snapshot. A camera-only scan (no points) keeps `head`'s
/// geometry; the caller refuses one when `head` has none (CameraOnlyWithoutGeometry), before
/// it stores any blob. Older cameras a revisit needs the pixels of are read through `images`
/// when given (the engine's, kept between ingests: LoadedCamera).
absl::StatusOr<FlowResult> IngestScan(store::ProjectStore& store, const store::Snapshot& head,
                                      const store::ScanInfo& info, const ingest::ScanInput& scan,
                                      int64_t max_image_pixels, const StageFn& stage = {},
                                      SourceImageCache* images = nullptr);

/// An RGBZ image sent back as derived data (§10).
struct BackProjectInput {
  std::string name;             ///< the batch's name (a scan of its own); empty: "backproject-<batch>"
  geometry::Pose pose;          ///< T_world_camera of the image, in its projection's frame
  bool pinhole = false;         ///< false: equirectangular
  geometry::PinholeIntrinsics intrinsics;  ///< pinhole only (size from the image)
  std::string image;            ///< OpenEXR bytes with channels R, G, B, Z [, N.x, N.y, N.z, U, A]
  int64_t render_id = 0;        ///< the render it came from (0: none)
  std::string request_id;       ///< the client's request id (ScanInput::request_id)
};

/// Back-projection (§10): validates `input` (image channels and size, pose, projection, cited
/// render, batch name) before storing anything, stores the image as the blob of the batch's
/// one derived source (a scan of its own, so that DeleteScan rolls the batch back), and makes
/// a new version whose records gain the image's derived records. Geometry does not change.
/// INVALID_ARGUMENT / RESOURCE_EXHAUSTED for bad input, NOT_FOUND for an unknown render,
/// ALREADY_EXISTS for a name in use, FAILED_PRECONDITION for a project without geometry.
/// @warning The caller serialises it with the project's other writers.
absl::StatusOr<FlowResult> BackProject(store::ProjectStore& store, const store::Snapshot& head,
                                       const BackProjectInput& input, int64_t max_image_bytes,
                                       int64_t max_image_pixels, const StageFn& stage = {});

/// A new version without scan `scan_name`: its vossels' sums are recomputed from the other
/// scans' blobs in the tiles it touched, and the older sources are revisited where the removed
/// geometry changes their depth panoramas (visibility can grow where geometry shrinks).
/// NOT_FOUND for an unknown scan.
absl::StatusOr<FlowResult> DeleteScan(store::ProjectStore& store, const store::Snapshot& head,
                                      const std::string& scan_name, int64_t max_image_pixels,
                                      const StageFn& stage = {},
                                      SourceImageCache* images = nullptr);

/// Recomputes the whole project from its blobs (geometry, every source's records and reach,
/// fusion) and commits it as a new version whose manifest replaces the previous one.
/// Tile by tile within `max_snapshot_bytes` (tile_budget.h): when the version, estimated from
/// the new geometry's tiles and HEAD's record counts, exceeds it, its tiles are made in groups
/// that fit, one after another (every source's visibility found whole and sampled on the
/// group's vossels, fused, and the group's tile objects put), and committed together; the
/// whole geometry is held throughout, as an ingest holds it. FAILED_PRECONDITION for a project
/// without scans.
absl::StatusOr<FlowResult> Rebuild(store::ProjectStore& store, int64_t max_image_pixels,
                                   int64_t max_snapshot_bytes, const StageFn& stage = {});

/// Fused values of one version under other profiles, loaded from its tiles once (thread-safe;
/// a few layers at most).
class FusedLayerCache {
 public:
  /// The layer's values for `version`, or null when not cached.
  std::shared_ptr<const records::FusedValues> Find(int64_t version, const std::string& layer);
  void Put(int64_t version, const std::string& layer, std::shared_ptr<const records::FusedValues> v);

 private:
  std::mutex mu_;
  int64_t version_ = -1;
  std::map<std::string, std::shared_ptr<const records::FusedValues>> layers_;
};

/// Decoded camera images within a byte budget: those of renders with ColourDetail::
/// kSourceImages (§8), by blob hash, and those revisits read (with their artefact maps, §9:
/// LoadedCamera; an 8-bit camera's as its codes, geometry::PackSrgb8), and LiDARs' points. What goes first is chosen by GreedyDual-Size (Cao and
/// Irani, 1997): each entry is worth the seconds it took to make per byte it holds, raised on
/// every use to the worth of the last entry evicted, and the least worth goes, the least
/// recently used among equals; entries of equal cost per byte go least recently used first.
/// A LiDAR reloads in a tenth of a camera's decode for half its bytes: a revisit that reads
/// more sources than the budget holds keeps its cameras (on the 12-station corridor, LRU
/// evicted each source just before its next use). Thread-safe.
class SourceImageCache {
 public:
  explicit SourceImageCache(int64_t budget_bytes) : budget_bytes_(budget_bytes) {}
  int64_t budget_bytes() const { return budget_bytes_; }
  /// The image kept under `key` (and, when asked, its artefact maps if kept), or null.
  std::shared_ptr<const geometry::LinearImage> Find(
      const std::string& key, std::shared_ptr<const ingest::ArtefactMaps>* artefacts = nullptr);
  /// Keeps `image` (and its `artefacts`, if any) under `key`, evicting others to stay within
  /// the budget; one larger than it is not kept, nor one under a key already kept.
  /// `cost_seconds`: what making it took (its decode), its worth per byte.
  void Put(const std::string& key, std::shared_ptr<const geometry::LinearImage> image,
           std::shared_ptr<const ingest::ArtefactMaps> artefacts = nullptr,
           double cost_seconds = 0.0);
  /// An image kept as its 8-bit codes (geometry::PackSrgb8) under `key`, or null; as Find.
  std::shared_ptr<const geometry::Srgb8Image> FindPacked(
      const std::string& key, std::shared_ptr<const ingest::ArtefactMaps>* artefacts = nullptr);
  /// Keeps `packed` (and its `artefacts`) under `key`, as Put keeps an image.
  void PutPacked(const std::string& key, std::shared_ptr<const geometry::Srgb8Image> packed,
                 std::shared_ptr<const ingest::ArtefactMaps> artefacts = nullptr,
                 double cost_seconds = 0.0);
  /// A LiDAR's points (with its range grid and gap fill) kept under `key`, or null; kept as
  /// images are, in the same budget.
  std::shared_ptr<const ingest::LidarSource> FindLidar(const std::string& key);
  void PutLidar(const std::string& key, std::shared_ptr<const ingest::LidarSource> lidar,
                double cost_seconds = 0.0);

 private:
  std::mutex mu_;
  const int64_t budget_bytes_;
  int64_t bytes_ = 0;
  uint64_t clock_ = 0;
  double inflation_ = 0.0;  ///< the worth of the last entry evicted (GreedyDual's L)
  struct Entry {
    std::shared_ptr<const geometry::LinearImage> image;
    std::shared_ptr<const geometry::Srgb8Image> packed;
    std::shared_ptr<const ingest::ArtefactMaps> artefacts;
    std::shared_ptr<const ingest::LidarSource> lidar;
    int64_t bytes = 0;
    uint64_t used = 0;
    double cost_per_byte = 0.0;
    double worth = 0.0;  ///< L at its last use plus its cost per byte
  };
  /// An image entry of `image_bytes` (with its artefact maps' bytes) worth `cost_seconds`.
  static Entry ImageEntry(int64_t image_bytes, std::shared_ptr<const ingest::ArtefactMaps> artefacts,
                          double cost_seconds);
  /// Keeps `entry` (its bytes counted) under `key`, evicting the least worth first.
  void Keep(const std::string& key, Entry entry);
  /// The entry kept under `key`, marked most recently used; empty when none.
  Entry Use(const std::string& key);
  std::map<std::string, Entry> entries_;
};

/// What a render query reads besides the snapshot.
struct RenderCaches {
  FusedLayerCache* fused = nullptr;        ///< required
  SourceImageCache* images = nullptr;      ///< required for ColourDetail::kSourceImages
  int64_t max_image_pixels = 0;            ///< decode limit of one image
};

/// The render query (§8) of `snapshot` under `profile`: the fused values are the version's
/// layer for the profile when every tile holds it (read once into the fused cache), else fused
/// from the records for this render (the image says so). With η > 0 or colour detail the
/// records are weighed under `profile` (§7) and scaled by its channel gains. With
/// ColourDetail::kSourceImages the cameras whose records lie on hit vossels are decoded (or
/// found in the image cache), most-hit first, as long as together they fit the cache's
/// budget; the others keep their records' colours (the image counts them). The render is
/// recorded in the catalog and gets its id.
absl::StatusOr<render::RenderImage> RenderQuery(store::ProjectStore& store,
                                               std::shared_ptr<const store::Snapshot> snapshot,
                                               const fusion::WeightingProfile& profile,
                                               const render::RenderRequest& request,
                                               const RenderCaches& caches);

/// RenderQuery of version `version` without holding it whole: its tiles are read nearest the
/// eye first, in groups that each fit `budget_bytes` (tile_budget.h), one after another, each
/// group rendered alone and composited by which hit cell each ray enters first
/// (render::CompositeNearer), so the image is the one RenderQuery gives of the whole version.
/// A tile that every ray through it has already stopped before is not read (render::RayReach).
/// Deep output takes one pass per layer. The image says how many groups and tiles it read
/// (RenderImage::tile_groups, tiles_read); its rows reach `request.rows_done` once the last
/// group is composited.
absl::StatusOr<render::RenderImage> RenderQueryInTiles(store::ProjectStore& store,
                                                      int64_t version,
                                                      const fusion::WeightingProfile& profile,
                                                      const render::RenderRequest& request,
                                                      const RenderCaches& caches,
                                                      int64_t budget_bytes);

/// What the catalog records of a render (its pose, projection, profile and version).
store::RenderRecord RenderRecordOf(const render::RenderRequest& request,
                                   const render::RenderImage& image);

/// One record of a provenance query, with its vossel and the §7 weight it gets under the
/// query's profile.
struct RecordRow {
  /// The vossel's ordinal among the query's vossels with records (0, 1, …; the rows of one
  /// vossel share it), which are taken tile by tile (key order), then by k.
  int32_t vossel = 0;
  openvdb::Coord coord;             ///< the vossel's index-space coordinate k
  Eigen::Vector3d centroid_m;       ///< the vossel's centroid (lattice frame; world at the facade)
  int32_t source = 0;               ///< record `scan` field: the source id
  int64_t scan_id = 0;              ///< the scan the source belongs to (0: unknown)
  std::string scan_name;
  std::string source_name;
  records::Modality modality = records::Modality::kUnspecified;
  std::array<float, records::kValueChannels> value{};
  float range_m = 0, cos_inc = 0, foot_major_m = 0, foot_minor_m = 0, vis = 0;
  std::array<float, 2> uv_px{};
  std::array<float, records::kConfidenceCount> conf{};
  int8_t flags = 0;
  int32_t batch = 0;
  float weight = 0;                 ///< w_{k,m} under the profile
};

/// Provenance query: every record of the vossels whose cells meet the world box
/// [min_m, max_m] (a point: min = max), in vossel (RecordRow::vossel) then source order, at
/// most `limit`
/// (`truncated` says when more matched). INVALID_ARGUMENT for a box with min > max or
/// non-finite corners.
struct RecordsQueryResult {
  std::vector<RecordRow> rows;
  int64_t vossels = 0;
  bool truncated = false;
  std::string profile;   ///< the profile the weights are under
  int32_t revision = 0;
};
absl::StatusOr<RecordsQueryResult> QueryRecords(const store::ProjectStore& store,
                                                const store::Snapshot& snapshot,
                                                const Eigen::Vector3d& min_m,
                                                const Eigen::Vector3d& max_m,
                                                const fusion::WeightingProfile& profile,
                                                int64_t limit);
/// QueryRecords of version `version` reading only the tiles the box meets, in groups that
/// each fit `budget_bytes` (tile_budget.h), one after another: the same answer.
absl::StatusOr<RecordsQueryResult> QueryRecordsInTiles(const store::ProjectStore& store,
                                                       int64_t version,
                                                       const Eigen::Vector3d& min_m,
                                                       const Eigen::Vector3d& max_m,
                                                       const fusion::WeightingProfile& profile,
                                                       int64_t limit, int64_t budget_bytes);

/// One artefact's confidence map of a camera image (VASL-MODEL §9) and how much of the image
/// it covers.
struct ArtefactMap {
  /// "saturation": saturation and blooming (DetectSaturation), readout smear multiplied in;
  /// "smear": readout smear alone (DetectSmear); "flare": veiling glare
  /// (DetectFlare); "codec": a JPEG's blocking, ringing and chroma (DetectCodec); "fringing":
  /// chromatic fringing, corrected (EstimateChannelShift), whose soft pixels are those the
  /// correction moved by more than a tenth of their light; "lens": the rig camera's dirt and
  /// fog map (fusion::LensMap), when a lens map applies to the camera, as the factor fusion puts
  /// on conf[dirt] at the image's own colours.
  std::string artefact;
  int64_t flagged_pixels = 0;    ///< confidence 0 (clipped; flare: invalid)
  int64_t soft_pixels = 0;       ///< 0 < confidence < 1 (a halo; flare: lowered by a veil)
  int regions = 0;               ///< connected clipped regions; flare: sources with a veil
  int max_extent_px = 0;         ///< the widest soft band around a region (flare: the farthest
                                 ///< affected pixel from its source), pixels
  double covered_fraction = 0.0; ///< share of the image's pixels below 1
  /// Fringing when found: red's (dx, dy) then blue's against green's, pixels (image-wide).
  std::vector<double> channel_offsets_px;
  /// Codec: the IJG quality of a JPEG's luma table (0: not a JPEG), and its chroma subsampling.
  double jpeg_quality = 0.0;
  bool chroma_subsampled = false;
  /// Smear: the largest column lift, a fraction of the clip level (regions: the columns).
  double smear_offset = 0.0;
  /// Lens dirt and fog ("lens"): the catalog id of the map that applies (fusion::LensMap).
  int64_t lens_map = 0;
  std::string png;               ///< the map, ingest::EncodeConfidencePng
};

/// The confidence maps of one camera of a scan.
struct SourceConfidence {
  int32_t source_id = 0;
  std::string source;  ///< the camera's name in its scan
  int width_px = 0;
  int height_px = 0;
  std::vector<ArtefactMap> artefacts;
};

/// The confidence maps of every camera of scan `scan` among `scans`, in source order: each
/// stored image decoded again (at most `max_pixels`) and its artefacts found as its ingest
/// found them. NOT_FOUND naming the scan; DATA_LOSS when a stored image cannot be read.
absl::StatusOr<std::vector<SourceConfidence>> ScanConfidence(
    const store::ProjectStore& store, const std::vector<store::ScanInfo>& scans,
    const std::string& project, const std::string& scan, int64_t max_pixels);

/// A visual reference of a scan among `scans` (their poses as the caller wants them) and its
/// image bytes as sent. NOT_FOUND naming the scan, or the reference and the ones it has.
absl::StatusOr<std::pair<store::VisualReferenceInfo, std::string>> VisualReference(
    const store::ProjectStore& store, const std::vector<store::ScanInfo>& scans,
    const std::string& project, const std::string& scan, const std::string& name);

/// A new version that gives back version `version` of the project: its manifest (every tile
/// and layer, shared, nothing rewritten), its counts and its live scans. NOT_FOUND when
/// retention removed it, INVALID_ARGUMENT for HEAD or a later version.
absl::StatusOr<FlowResult> Rollback(store::ProjectStore& store, int64_t version,
                                    const StageFn& stage = {});

/// What Export wrote.
struct ExportResult {
  int64_t version = 0;
  int64_t vossel_count = 0;
  int64_t record_count = 0;
  int64_t size_bytes = 0;
};

/// The export query: one self-contained OpenVDB file at `path` holding every layer of
/// `snapshot` (records::WriteVersionFile), for tools that want one file (Houdini, Blender,
/// vdb_print).
/// The grids' transforms place the vossels in world coordinates (lattice + `origin_m`, §1),
/// which the file also keeps as metadata; values that are positions (centroid) stay in the
/// lattice's frame, where a float keeps them.
absl::StatusOr<ExportResult> Export(const store::Snapshot& snapshot,
                                    const Eigen::Vector3d& origin_m,
                                    const std::filesystem::path& path);

}  // namespace vasl::flows

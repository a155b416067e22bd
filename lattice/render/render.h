/// @file render.h
/// @brief The VASL rendering equation (VASL-MODEL §8): an equirectangular RGBZ + normal +
///        uncertainty image from any pose, by hierarchical DDA over the lattice.
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "lattice/geometry/image_projection.h"
#include "lattice/geometry/linear_image.h"
#include "lattice/geometry/pinhole.h"
#include "lattice/geometry/pose.h"
#include "lattice/records/records.h"

namespace vasl::render {

/// Most surface layers a deep render keeps per pixel.
inline constexpr int kMaxLayers = 8;

/// How a render's pixels map to rays.
enum class Projection {
  kEquirect,  ///< §2.1: W columns span 2π of azimuth, H rows π of elevation; sensor frame x forward, z up
  kPinhole,   ///< §2.2: `pinhole` intrinsics and distortion; camera frame x right, y down, z forward
};

/// Where a hit pixel's colour comes from (§8).
enum class ColourDetail {
  kVossel,  ///< the vossel's colour: fused C_k (η = 0) or its records' C_{k,m} (η > 0)
  /// The sources' images at the hit point: each colour record's C_{k,m} is read again where
  /// the pixel's own point x = o + Z·d projects into its source's image (bilinear), so colour
  /// varies within a vossel as finely as the images resolve; the §7 weights (and the view term)
  /// blend them as they blend C_{k,m}. A record whose source has no image here (point colour,
  /// derived data, an image beyond the budget, x outside a pinhole photo) keeps its C_{k,m}.
  kSourceImages,
};

struct RenderImage;
/// What to render (§8).
struct RenderRequest {
  geometry::Pose pose;          ///< T_world_camera (the projection's own camera frame)
  int width_px = 2048;          ///< W: equirect columns spanning 2π, or pinhole image width
  int height_px = 1024;         ///< H: equirect rows spanning π, or pinhole image height
  Projection projection = Projection::kEquirect;
  /// Pinhole intrinsics and distortion (width and height are the request's); pinhole only.
  geometry::PinholeIntrinsics pinhole;
  int64_t version = 0;          ///< 0: HEAD
  int layers = 1;               ///< L: successive surface hits kept per pixel (deep output), 1..kMaxLayers
  std::string profile;          ///< weighting profile (§7); empty: the project's active one
  int32_t profile_revision = 0; ///< 0: the profile's latest revision
  double eta = 0.0;             ///< view term η (§8); 0 uses the fused colour C_k
  ColourDetail colour_detail = ColourDetail::kVossel;
  double max_range_m = 1000.0;  ///< rays stop here
  /// Asked before each row is marched, from several threads (may be empty): a status other
  /// than OK stops the render with that status (the caller cancelled, or its deadline passed).
  std::function<absl::Status()> interrupt;
  /// Rows as they become final, for a caller that streams them (may be empty): called with
  /// [row_begin, row_end) in row order, each row once, never concurrently, from one of the
  /// render's threads, once the image's per-pixel arrays hold those rows' final values (its
  /// counts are final only when the render returns). Rows are marched in bands of kBandRows
  /// taken in order, so they arrive steadily while the rest is marched. With
  /// ColourDetail::kSourceImages rows become final in ApplyColourDetail, which calls it.
  /// A status other than OK stops the render with that status.
  std::function<absl::Status(const RenderImage& image, int row_begin, int row_end)> rows_done;
  /// Keep RenderImage::vossel_index whatever the colour detail: for a caller that composites
  /// renders of parts of a version (CompositeNearer).
  bool keep_vossel_index = false;
  /// Per pixel, the range (metres) from which its ray looks for a surface (+inf: the pixel is
  /// not marched); null: 0. For a caller that renders a version's deeper layers part by part.
  const std::vector<float>* start_range_m = nullptr;
};
/// A deeper layer starts this many vossels beyond the one in front *(choice)*: surfaces nearer
/// each other than the lattice resolves are one surface, and the same surface's next vossels
/// (a wall two vossels thick) are not a layer of their own.
inline constexpr double kLayerGapVox = 1.5;
/// Rows per band of a render's march: the unit of its work and of RenderRequest::rows_done
/// (the EXR encoder gathers bands into runs of 32 rows per thread before OpenEXR compresses them).
inline constexpr int kBandRows = 16;

/// A rendered equirectangular RGBZ + normal + uncertainty image (§8), row-major, row 0 up.
struct RenderImage {
  int width_px = 0;                ///< W, pixels
  int height_px = 0;               ///< H, pixels
  int64_t version = 0;             ///< version rendered
  std::string profile;             ///< profile whose fused values it shows
  int32_t profile_revision = 0;
  bool fused_on_the_fly = false;   ///< the version holds no fused tiles for it: fused for this render
  int64_t render_id = 0;           ///< the id the project's catalog recorded it under (0: none)
  std::vector<float> rgb;          ///< 3 per pixel, linear; 0 where no hit
  std::vector<float> depth_m;      ///< 1 per pixel: range along the ray; +inf where no hit
  std::vector<float> normal;       ///< 3 per pixel, world frame; 0 where no hit
  std::vector<float> uncertainty;  ///< 1 per pixel: U_k; 0 where no hit; +inf where the hit has no colour
  /// 1 per pixel: coverage. 1 where the ray hit a vossel that has colour; 0 where it hit
  /// nothing, or hit a vossel without any colour record of positive weight (§8: no colour is
  /// not black; its rgb stays 0 and U = +inf).
  std::vector<float> alpha;
  int64_t colourless_pixels = 0;   ///< hit pixels whose vossel has no colour
  /// Multi-layer depth (§8), when the request asked for layers > 1: per pixel, its successive
  /// surface hits front to back (the first is the image's own), at most `layers`.
  int layers = 1;
  std::vector<uint8_t> layer_count;  ///< hits kept per pixel
  std::vector<float> deep_depth_m;   ///< layers per pixel; +inf past layer_count
  std::vector<float> deep_rgb;       ///< 3 per layer and pixel
  std::vector<float> deep_alpha;     ///< 1 per layer and pixel: 1 where the surface has colour
  int64_t hit_pixels = 0;          ///< pixels whose ray met a vossel within max_range_m
  /// Per pixel, the vossel its ray hit (-1: none); kept only for a kSourceImages render.
  std::vector<int32_t> vossel_index;
  /// kSourceImages: sources whose image coloured some pixel, and sources with records on hit
  /// vossels whose image was left out (not decodable here, or beyond the byte budget).
  int64_t detail_sources = 0;
  int64_t detail_sources_skipped = 0;
  /// Groups of tiles the version was rendered in, one after another, so that what the render
  /// held at once stayed within the engine's memory budget (1: the version at once).
  int tile_groups = 1;
  /// Of the version's tiles, those such a render read: the others lay behind what every ray
  /// through them had already hit (RayReach). Both 0 for a render of the version at once.
  int64_t tiles_read = 0;
  int64_t tiles_total = 0;
};

/// A source's image as the colour detail reads it (§2.1 or §2.2 through its pose).
struct DetailImage {
  geometry::Pose pose;                  ///< T_world_camera, the lattice frame
  geometry::ImageProjection projection; ///< of `image` (its width and height)
  std::shared_ptr<const geometry::LinearImage> image;  ///< 3 channels, linear; null: none
  /// Corrects a colour read at continuous pixel uv in place as the profile reads the source's
  /// records there (fusion::RecordValues::CorrectImageSample: the §9 lens map); empty: none.
  std::function<void(const float* uv, float* rgb)> correct;
};

/// What the §8 view term (η > 0) reads besides the fused values: every vossel's records with
/// their §7 weights (fusion::RecordWeights), and where each source stood.
struct ViewBlendInputs {
  const records::RecordSet* records = nullptr;  ///< sorted by vossel
  const std::vector<float>* weight = nullptr;   ///< w_{k,m} per record
  const std::vector<size_t>* begin = nullptr;   ///< vossel k's records: [begin[k], begin[k+1])
  /// o_m, world metres, indexed by source id (record `scan`); non-finite for unknown ids.
  std::vector<Eigen::Vector3d> source_origin_m;
  /// a_{m,c} of the profile (§7) by source id (fusion::DenseChannelGains); empty or short: 1.
  std::vector<std::array<float, 3>> channel_gain;
  /// Each record's value as fusion reads it under the profile (fusion::RecordValues: §9 lens
  /// map applied, then a_{m,c}), 3 per record; null: the record's value times channel_gain.
  const std::vector<float>* value = nullptr;
  /// kSourceImages: each source's image by source id; short or null image: none.
  std::vector<DetailImage> images;
};

/// Renders `request` from a version's geometry and fused values (§8). Parallel over rows (TBB).
/// @details Each pixel's ray (the projection's inverse at the pixel centre, §2.1 or §2.2,
///          rotated by the pose) is marched
///          by hierarchical DDA over `geometry.index_grid` (empty space skipped per node); the
///          first active vossel whose plane (x_k, n_k) the ray crosses at range ≥ 0 inside the
///          vossel's cell, expanded by internal::kDefaultCellMarginVox (0.25 h) to close cracks
///          between neighbouring planes, and on the patch its points cover (an ellipse of their
///          in-plane covariance, for vossels of ≥ 8 points; render.cc WithinPointExtent), is
///          the hit: Z = range to that plane, N = n_k turned
///          toward the camera, C = fused rgb C_k (0 if its rgb weight is 0; such vossels still
///          occlude) when η = 0; when η > 0, C = Σ w·max(0, v_{k,m}·v_{k,o})^η·C_{k,m} / Σ (same
///          weights) over the vossel's rgb and derived records (v the unit vectors from x_k to
///          the source and to the render origin), falling back to C_k when no record faces the
///          view (choice); U = rgb U_k. A hit vossel without colour of positive weight gets
///          alpha 0, rgb 0 and U = +inf (also when `fused` has no rgb modality). A vossel
///          with a zero normal is hit where the ray enters its cell, with N = 0.
///          `image.version` is copied from the request (the engine sets the resolved version).
///          With ColourDetail::kSourceImages the image keeps each pixel's vossel index for
///          ApplyColourDetail, which the caller runs once it has the sources' images.
/// @return INVALID_ARGUMENT for a non-positive or over-large (> 2^28 pixels) size, η < 0,
///         η > 0 without `blend` or with inconsistent blend inputs, max_range_m ≤ 0, a
///         non-unit pose quaternion, a null index grid or one whose transform is not linear and
///         uniform, geometry/fused arrays whose sizes disagree, or an index grid holding a vossel
///         index outside [0, geometry.size()).
/// @warning Thread-safe: reads its inputs only (each TBB task uses its own ValueAccessor).
/// Recolours the hit pixels of `image` (rendered from `request` with kSourceImages, so that it
/// keeps its vossel indices) from the sources' images at each pixel's own point (§8,
/// ColourDetail::kSourceImages): C = Σ w·f·a·I_m(π_m(x)) / Σ w·f over the hit vossel's rgb and
/// derived records of positive weight w (f = max(0, v_{k,m}·v_{k,o})^η, 1 when η = 0; a the
/// channel gain), I_m(π_m(x)) corrected by its DetailImage::correct (a §9 lens map) and
/// replaced by C_{k,m} where source m has no image. Pixels
/// without colour stay so; sets image.detail_sources. Parallel over rows (TBB).
/// @return INVALID_ARGUMENT when the image kept no vossel indices or the blend inputs are
///         missing or disagree with the geometry.
absl::Status ApplyColourDetail(const records::VosselGeometry& geometry,
                               const RenderRequest& request, const ViewBlendInputs& blend,
                               RenderImage* image);

absl::StatusOr<RenderImage> RenderEquirect(const records::VosselGeometry& geometry,
                                           const records::FusedValues& fused,
                                           const RenderRequest& request,
                                           const ViewBlendInputs* blend = nullptr);

/// An image of `request`'s size, layers and projection with no hit, as a render of no vossel
/// gives, with its vossel indices (all -1) when the request keeps them (kSourceImages or
/// keep_vossel_index): what a render and CompositeNearer start from.
RenderImage EmptyRender(const RenderRequest& request);

/// Composites `part`, a render of `request` over some tiles of a version that kept its vossel
/// indices into `part_geometry`, into `*into`, a composite of renders of the same request over
/// other tiles (EmptyRender at first): each pixel keeps the hit whose cell its ray enters
/// first, so that the composite of renders over disjoint tiles is the render over all of them
/// (§8: the first vossel along the ray; two cells the ray enters at the same range, across an
/// edge or a corner, are told by their depth). `entry` holds each pixel's entry range (metres)
/// into `*into`'s hit cell; start it empty. Pixel values, normal, U, alpha and the first deep
/// layer (when both have layers) follow the hit; the counts are recomputed.
absl::Status CompositeNearer(const RenderRequest& request,
                             const records::VosselGeometry& part_geometry,
                             const RenderImage& part, RenderImage* into,
                             std::vector<double>* entry);

/// Which boxes of the lattice the rays of a request can still reach in front of the hits a
/// composite holds (CompositeNearer's `entry`): so that a caller rendering a version part by
/// part, nearest parts first, skips the parts every ray through them has already stopped
/// before. Rays are bundled in blocks of kReachBlockPx² pixels, each bounded by a cone of the
/// directions of its pixel centres; a block's rays can reach a box when its cone meets the
/// box's bounding cone from the eye and its farthest entry range (+inf while a pixel has no hit)
/// is not nearer than the box. Exact: a skipped box cannot hold the hit of any pixel.
class RayReach {
 public:
  static constexpr int kReachBlockPx = 16;
  explicit RayReach(const RenderRequest& request);
  /// Takes the composite's entry ranges (one per pixel; empty: no hit yet).
  void Update(const std::vector<double>& entry);
  /// Whether some ray within the request's max range can enter the box [lo, hi] (lattice
  /// metres) before it meets a hit of the composite.
  bool MayReach(const Eigen::Vector3d& lo, const Eigen::Vector3d& hi) const;

 private:
  Eigen::Vector3d eye_;
  double max_range_m_ = 0.0;
  int width_ = 0, height_ = 0, blocks_x_ = 0, blocks_y_ = 0;
  std::vector<Eigen::Vector3d> axis_;  ///< per block: the direction of its centre
  std::vector<double> half_rad_;       ///< per block: the cone's half angle
  std::vector<double> farthest_m_;     ///< per block: max entry range of its pixels
};

/// Hands `image`'s rows to request.rows_done (if any) in bands of kBandRows, in row order.
absl::Status EmitRows(const RenderRequest& request, const RenderImage& image);

}  // namespace vasl::render

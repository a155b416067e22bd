/// @file sources.h
/// @brief Decoded observation sources as the ingest stages consume them: the LiDAR of a scan
///        (points in its sensor frame) and its cameras (linear images), each with its pose and
///        its source id (the `scan` field of its records, VASL-MODEL §6).
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "lattice/geometry/linear_image.h"
#include "lattice/geometry/pinhole.h"
#include "lattice/geometry/pose.h"
#include "lattice/ingest/scan_input.h"
#include "lattice/records/records.h"

namespace vasl::ingest {

/// A decoded image (geometry/linear_image.h: shared with the render's colour detail).
using geometry::LinearImage;

/// Decodes PNG, JPEG, EXR or TIFF bytes with OpenImageIO. Integer encodings are taken as sRGB
/// and linearised, unless the file says they are linear; float encodings are linear already.
/// Keeps 3 channels (gray is replicated) or, for an `infrared` camera's image, the first; and
/// an infrared image's 16-bit integer codes are radiometric counts, read linearly as
/// code / 65535 (decision: a thermal camera's 16-bit PNG or TIFF holds codes proportional to
/// radiance, and its PNG says sRGB only because that is PNG's default; §6 stores linear
/// radiometry), while its 8-bit codes are a display image's, sRGB like any other.
/// An alpha channel is the pixels' coverage (LinearImage::alpha, kept only when some pixel is
/// not whole): integer alpha codes are linear, code / full scale; the colour is associated
/// with it after linearisation (a PNG's or TIFF's unassociated colour times alpha; an EXR's is
/// associated already), and the colour channels are the first three that are not alpha.
/// INVALID_ARGUMENT when the bytes do not decode or the image is empty; RESOURCE_EXHAUSTED
/// above `max_pixels`.
absl::StatusOr<LinearImage> DecodeImage(std::string_view bytes, bool infrared,
                                        int64_t max_pixels);

/// Applies a camera's mask image (PNG, JPEG, EXR or TIFF bytes of `image`'s size) to `image`
/// as coverage: the mask's first channel over its largest value (0 where it is 0 or NaN, and
/// everywhere when no value is positive; decision: so that a 0/1 mask and a 0/255 one mean the
/// same, as an E57 imageMask's non-zero pixels are the valid ones) multiplies the image's alpha
/// (LinearImage::alpha; created) and its associated colour. A mask that covers every pixel
/// leaves the image as it was. INVALID_ARGUMENT when the mask does not decode or is not the
/// image's size; RESOURCE_EXHAUSTED above `max_pixels`.
absl::Status ApplyMask(std::string_view mask_bytes, int64_t max_pixels, LinearImage& image);

/// `image` (a decoded panorama of part of the sphere, after its mask) placed at `window` in the
/// whole sphere's panorama: outside it no colour and no coverage (LinearImage::alpha 0),
/// inside it the image's own pixels and coverage; `coded_window` says where it lies, so that
/// the codec's blocks are found where the file had them (DetectCodec). INVALID_ARGUMENT when
/// it does not fit (CheckSphereWindow); RESOURCE_EXHAUSTED above `max_pixels`.
absl::Status PlaceInSphere(const SphereWindow& window, int64_t max_pixels, LinearImage& image);

/// Where a cylindrical image lies once resampled into its sphere.
struct CylinderPlacement {
  SphereWindow window;  ///< the sphere, and the resampled image's top-left pixel in it
  int rows = 0;         ///< the sphere's rows it covers, from window.top_px
};
/// The whole sphere's panorama a cylindrical image of `width_px` × `height_px` is resampled
/// into (at its azimuth pitch: π / pixel_width_rad rows, twice as many columns) and where it
/// lies there: its columns centred, its rows those whose centre's elevation lies within the
/// cylinder's. INVALID_ARGUMENT for a cylinder that is not one (a pitch outside (0, 0.1] rad, a
/// pixel height or radius not > 0, a principal row not finite), an image wider than 360°, or
/// one that covers no row of the sphere.
absl::StatusOr<CylinderPlacement> CylinderWindow(const CylinderImage& cylinder, int width_px,
                                                 int height_px);

/// `image` (a decoded cylindrical panorama, after its mask) resampled into the equirect rows of
/// its CylinderWindow (each row read at its elevation's cylinder row, linearly between the two
/// nearest; columns as they are) and placed there (PlaceInSphere). The image is no longer its
/// file's pixels: its codec's blocks are gone (`coding` null: no codec map). INVALID_ARGUMENT
/// as CylinderWindow; RESOURCE_EXHAUSTED above `max_pixels`.
absl::Status CylinderToSphere(const CylinderImage& cylinder, int64_t max_pixels,
                              LinearImage& image);

/// Whether an image of `width_px` × `height_px` fits `window`: the sphere twice as wide as high
/// (within 2.5%) and the image within it. INVALID_ARGUMENT saying why not.
absl::Status CheckSphereWindow(const SphereWindow& window, int width_px, int height_px);

/// The quantisation tables and chroma subsampling of JPEG bytes (baseline, extended or
/// progressive DCT with Huffman coding), read from their DQT and SOF markers; null for other
/// bytes, other JPEG processes (lossless, arithmetic) or a damaged header. DecodeImage sets it
/// as a decoded JPEG's LinearImage::coding.
std::shared_ptr<const geometry::BlockCoding> ReadJpegCoding(std::string_view bytes);

/// What an image's header says, read without decoding its pixels.
struct ImageHeader {
  int width_px = 0;
  int height_px = 0;
  int channels = 0;  ///< as stored
};

/// Reads the header of PNG, JPEG, EXR or TIFF bytes and makes the checks DecodeImage makes
/// before it allocates (a non-empty image, at most 16 channels, at most `max_pixels`), with
/// its codes; the pixels are not decoded, and may still fail to.
absl::StatusOr<ImageHeader> ProbeImage(std::string_view bytes, int64_t max_pixels);

/// The gap-fill points BinLidar adds for a LiDAR with a range grid, in its order: each point's
/// lattice position and the three returns of the triangle it lies on with its barycentric
/// weights, so that a sample of the returns (intensity, colour) can be interpolated there.
struct GapFillPoints {
  std::vector<Eigen::Vector3d> x;
  std::vector<std::array<uint32_t, 3>> corner;
  std::vector<std::array<float, 3>> weight;
  size_t size() const { return x.size(); }
};

/// The LiDAR of a scan.
struct LidarSource {
  int32_t id = 0;                     ///< source id (record `scan`)
  int32_t batch = 0;                  ///< batch of its records
  geometry::Pose pose;                ///< T_world_scanner
  double divergence_rad = 0.3e-3;     ///< θ_div (§3)
  std::vector<float> xyz_sensor_m;    ///< 3 per point, sensor frame
  std::vector<float> intensity;       ///< 1 per point; empty: every return counts as 1
  /// Per-point colour (E57 colorRed/Green/Blue), 3 per point, linear; empty: none. Its records
  /// belong to a source of their own (`colour_id`): the colour of the returns, seen from the
  /// scanner's origin (PointColourRecords).
  std::vector<float> rgb;
  int32_t colour_id = 0;              ///< source id of the colour records; 0: no colour source
  /// The scan's range grid, when the scanner gave one (E57 rowIndex / columnIndex): rows ×
  /// columns cells, and per point its cell row·columns + column. Empty: an unordered scan.
  int32_t grid_rows = 0, grid_columns = 0;
  std::vector<uint32_t> grid_cell;
  /// Its gap fill at the project's vossel size, when already computed (BinnedLidar::fill);
  /// null: GapFill computes it.
  std::shared_ptr<const GapFillPoints> gap_fill;
  size_t point_count() const { return xyz_sensor_m.size() / 3; }
  bool HasGrid() const { return grid_rows > 0 && grid_columns > 0 && !grid_cell.empty(); }
};

struct ArtefactMaps;  // artefacts.h

/// A camera of a scan: an equirectangular panorama (§2.1) or a pinhole photo (§2.2).
struct CameraSource {
  int32_t id = 0;                     ///< source id (record `scan`)
  int32_t batch = 0;
  geometry::Pose pose;                ///< T_world_camera
  records::Modality modality = records::Modality::kRgb;
  LinearImage image;                  ///< the decoded image, or empty with `load` set
  /// Decodes the image on demand when `image` is empty, so that a project's panoramas are
  /// held in memory one at a time (a decoded 8192×4096 panorama takes 400 MB).
  std::function<absl::StatusOr<LinearImage>()> load;
  /// Set with `load` and `artefacts` (an image kept as its 8-bit codes): decodes rows
  /// [row_begin, row_end) alone, as a band (LinearImage::row_origin), for records that read
  /// those rows only (CameraRecords: a revisit's few blocks). `image` then holds the image's
  /// size without pixels.
  std::function<absl::StatusOr<LinearImage>(int row_begin, int row_end)> load_rows;
  double angular_resolution_rad = 0.0;  ///< 0: θ_pix from the image size (§3)
  /// Set: a pinhole camera (its width and height are the image's); unset: equirectangular.
  std::optional<geometry::PinholeIntrinsics> pinhole;
  /// §9: the artefact maps of `image` as decoded, when already found (a cache's); unset: the
  /// records find them.
  std::shared_ptr<const ArtefactMaps> artefacts;
  /// The decoded image as a cache keeps it, shared rather than copied, with its channel shift
  /// (§9 fringing, found in `artefacts`) already corrected; read instead of `image` when set.
  std::shared_ptr<const LinearImage> kept_image;

  /// The image the records read: the kept one, or `image`.
  const LinearImage& Decoded() const { return kept_image ? *kept_image : image; }
};

/// An RGBZ[N,U,A] image sent back as derived data (§10): a render, edited or refined.
struct DerivedImage {
  int width_px = 0;
  int height_px = 0;
  std::vector<float> rgb;          ///< 3 per pixel, linear
  std::vector<float> depth_m;      ///< range along each pixel's ray; non-finite: no surface
  std::vector<float> normal;       ///< 3 per pixel (world), or empty
  std::vector<float> uncertainty;  ///< 1 per pixel, or empty
  std::vector<float> alpha;        ///< 1 per pixel coverage, or empty (every finite Z counts)
  /// A deep image (successive surfaces per pixel, §8 multi-layer depth): the pixel of each
  /// sample, in pixel order; rgb, depth_m and alpha then hold one entry per sample, and normal
  /// and uncertainty are empty. Empty: a flat image, one sample per pixel.
  std::vector<uint32_t> sample_pixel;

  /// Samples the image holds: one per pixel, or the deep image's.
  size_t SampleCount() const {
    return sample_pixel.empty() ? size_t(width_px) * size_t(height_px) : sample_pixel.size();
  }
};

/// A derived source: an image with its pose and projection, back-projected into records (§10).
struct DerivedSource {
  int32_t id = 0;                  ///< source id (record `scan`)
  int32_t batch = 0;
  geometry::Pose pose;             ///< T_world_camera of the image (the projection's frame)
  bool pinhole = false;            ///< false: equirect (§2.1)
  geometry::PinholeIntrinsics intrinsics;  ///< when pinhole (width and height are the image's)
  DerivedImage image;              ///< decoded, or empty with `load` set
  std::function<absl::StatusOr<DerivedImage>()> load;
};

struct SourceSet {
  std::vector<LidarSource> lidars;
  std::vector<LidarSource> point_colours;  ///< LiDARs with `rgb`, as colour sources
  std::vector<CameraSource> cameras;
  std::vector<DerivedSource> derived;
};

}  // namespace vasl::ingest

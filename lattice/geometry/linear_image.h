/// @file linear_image.h
/// @brief A decoded image in linear radiometry and its bilinear read at continuous pixel
///        coordinates (§2.1: pixel centres at half-integers): one implementation for the ingest
///        samplers (§4) and the render's colour detail (§8).
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <vector>

#include "lattice/memory/buffer_pool.h"

namespace vasl::geometry {

/// How a block-transform codec (baseline or progressive JPEG) coded an image: its quantisation
/// tables and its chroma subsampling, as the file declares them (VASL-MODEL §9 codec).
struct BlockCoding {
  std::array<uint16_t, 64> luma_q{};    ///< luma quantisation steps, row-major 8×8 (u fastest)
  std::array<uint16_t, 64> chroma_q{};  ///< chroma's; equal to luma's when the file has one table
  int chroma_step_x = 1;                ///< luma pixels per chroma sample across (2: 4:2:0, 4:2:2)
  int chroma_step_y = 1;                ///< and down (2: 4:2:0)
};

/// A rectangle of an image's pixels: columns [left, left + width), rows [top, top + height).
struct ImageWindow {
  int left_px = 0, top_px = 0, width_px = 0, height_px = 0;
};

/// A decoded image, row-major, row 0 at the top, linear radiometry.
struct LinearImage {
  int width_px = 0;
  int height_px = 0;
  int channels = 0;            ///< 1 or 3
  std::vector<float> pixels;   ///< width·height·channels values (a band's: its rows' alone)
  /// The first row `pixels` holds: 0 for a whole image. A band (UnpackSrgb8Rows) holds rows
  /// [row_origin, row_origin + pixels.size() / (width·channels)) of its height_px rows: what a
  /// reader of those rows alone needs (a revisit's samples). Reads (SampleBilinear) index it
  /// by the image's own rows.
  int row_origin = 0;
  /// The share of each pixel the image covers (its alpha channel: a stitcher's transparent
  /// nadir, a masked rig or operator), width·height values in [0, 1]; empty: every pixel
  /// whole. Where set, `pixels` hold colour times coverage (associated alpha), so that a
  /// bilinear read of both, divided, is the colour of the covered part alone.
  std::vector<float> alpha;
  float clip_value = 0.0f;     ///< linear value at which the encoding clips (1 for 8/16-bit); 0: none
  /// The block codec that coded it, decoded from 8-bit sRGB codes (a JPEG); null: none.
  std::shared_ptr<const BlockCoding> coding;
  /// Set when the file decoded is only part of this image (a partial panorama placed in its
  /// sphere, ingest::PlaceInSphere): where it lies, and where its codec's blocks start.
  std::optional<ImageWindow> coded_window;

  LinearImage() = default;
  LinearImage(const LinearImage&) = default;
  LinearImage(LinearImage&&) = default;
  LinearImage& operator=(const LinearImage&) = default;
  LinearImage& operator=(LinearImage&&) = default;
  /// Its buffers go back to memory's pool: a revisit unpacks a panorama of tens of megabytes
  /// per older camera, one after another (UnpackSrgb8Rows takes them again).
  ~LinearImage() {
    memory::GiveFloats(std::move(pixels));
    memory::GiveFloats(std::move(alpha));
  }

  /// Bytes its pixels take.
  std::size_t ByteSize() const { return (pixels.size() + alpha.size()) * sizeof(float); }
  /// The rows `pixels` (and `alpha`, where set) hold from row_origin: height_px for a whole
  /// image, fewer for a band.
  int HeldRows() const;
};

/// The standard sRGB EOTF (IEC 61966-2-1): encoded [0, 1] → linear, c/12.92 up to 0.04045,
/// else ((c + 0.055)/1.055)^2.4. How integer images are linearised (ingest::DecodeImage).
float SrgbToLinear(float encoded);
/// The standard sRGB OETF: linear [0, 1] → encoded [0, 1], piecewise 12.92·c below 0.0031308,
/// else 1.055·c^(1/2.4) − 0.055. Input clamped to [0, 1]; NaN → 0. How renders are written
/// (render::EncodePng) and a JPEG's codes are recovered (ingest::DetectCodec).
float LinearToSrgb(float linear);
/// The 8-bit sRGB code of a linear value, lround(255·LinearToSrgb(linear)) exactly, by two
/// small tables instead of a pow: how PNG renders are written (render::RowEncoder), 25 M
/// channels for a 4096×2048 image.
uint8_t LinearToSrgb8(float linear);

/// The linear value of each 8-bit sRGB code, SrgbToLinear(code / 255): how DecodeImage
/// linearises an 8-bit image.
const std::array<float, 256>& Srgb8ToLinear();

/// An image whose every value is an 8-bit code's linear value (Srgb8ToLinear), as DecodeImage
/// makes of an 8-bit file, kept as those codes: a quarter of the bytes, and the same image
/// back value for value. How the revisit cache keeps decoded camera images (flows::
/// SourceImageCache), so that it holds four times as many.
struct Srgb8Image {
  LinearImage header;          ///< size, channels, clip value and coding; no pixels
  std::vector<uint8_t> codes;  ///< one per value of the image's `pixels`, in their order
  std::size_t ByteSize() const { return codes.size(); }
};
/// `image` as its codes, or nullopt when some value is not an 8-bit code's linear value bit
/// for bit (a 16-bit or float image, one with alpha, or one changed since its decode).
/// Parallel (TBB).
std::optional<Srgb8Image> PackSrgb8(const LinearImage& image);
/// The image `packed` holds, bit for bit as packed. Parallel (TBB).
LinearImage UnpackSrgb8(const Srgb8Image& packed);
/// Rows [row_begin, row_end) of that image (clamped to it) as a band (LinearImage::
/// row_origin): each value bit for bit UnpackSrgb8's, for a reader of those rows alone.
LinearImage UnpackSrgb8Rows(const Srgb8Image& packed, int row_begin, int row_end);

/// Bilinear read of `img` at continuous pixel coordinates (u, v): `img.channels` values into
/// `out`. Columns wrap across the seam (`wrap`, a panorama) or clamp, rows clamp to the image
/// (and, of a band, to the rows it holds: its reader reads no others). (Saturation is read from
/// its own map, ingest::DetectSaturation.)
void SampleBilinear(const LinearImage& img, double u, double v, bool wrap, float* out);

/// Bilinear read of `img`'s coverage (`alpha`) at (u, v), as SampleBilinear reads its pixels;
/// 1 for an image without alpha. A colour read there, divided by it, is the covered part's.
float SampleCoverage(const LinearImage& img, double u, double v, bool wrap);

/// The covered part's colour at (u, v) into `out` (SampleBilinear's read divided by the
/// coverage there; zeros where nothing is covered), and that coverage: 1 for an image without
/// alpha, whose read is SampleBilinear's.
float SampleCovered(const LinearImage& img, double u, double v, bool wrap, float* out);

/// The coverage a read of an image must have to count (ingest::SampleCamera's records, the
/// render's colour detail): at least half of it on pixels the image covers.
inline constexpr float kCoveredAtLeast = 0.5f;

}  // namespace vasl::geometry

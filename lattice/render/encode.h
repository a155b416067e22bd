/// @file encode.h
/// @brief Encoders of a RenderImage: multi-channel float EXR (R,G,B,Z,N.x,N.y,N.z,U) through
///        OpenEXR, and an 8-bit sRGB PNG preview through OpenImageIO (VASL-MODEL §8 outputs).
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "lattice/geometry/linear_image.h"
#include "lattice/render/render.h"

namespace vasl::render {

/// The encodings of a render (§8 outputs).
enum class ImageFormat {
  kExr,      ///< EncodeExr's channels
  kDeepExr,  ///< EncodeDeepExr's samples
  kPng,      ///< EncodePng's preview
};

/// Where an encoder's bytes go: `bytes` belong at byte `offset` of the encoded file. Runs come
/// in the order the encoder writes them, and a later run may overwrite bytes of an earlier one
/// (OpenEXR fills its chunk offset table, reserved after the header, last): a reader rebuilds
/// the file by writing every run at its offset. A status other than OK stops the encoder with
/// that status (the reader went away).
using ByteSink = std::function<absl::Status(int64_t offset, std::string_view bytes)>;

/// A ByteSink that assembles the file into `*file` (each run written at its offset).
ByteSink AssembleInto(std::string* file);

/// Encodes a render's rows as they become final, so that a large render's file streams while
/// the rest is still marched (§8 outputs). The bytes equal those of EncodeExr, EncodeDeepExr or
/// EncodePng of the whole image, however the rows are split.
class RowEncoder {
 public:
  /// An encoder of a width_px × height_px image in `format`; writes its header to `sink`.
  /// @return INVALID_ARGUMENT for a non-positive size; INTERNAL when the codec fails.
  static absl::StatusOr<std::unique_ptr<RowEncoder>> Create(ImageFormat format, int width_px,
                                                            int height_px, ByteSink sink);
  virtual ~RowEncoder() = default;
  /// Encodes rows [row_begin, row_end) of `image`, which has the encoder's size; calls come in
  /// row order, each starting where the previous ended (0 first), and send the bytes they
  /// complete to the sink before they return. An encoder may hold rows back to encode them
  /// with later ones (rows_sent says how far its bytes have gone); the last row sends all.
  /// @return INVALID_ARGUMENT for rows out of order or an image whose arrays disagree with its
  ///         size; the sink's status when it stopped; INTERNAL when the codec fails.
  virtual absl::Status WriteRows(const RenderImage& image, int row_begin, int row_end) = 0;
  /// Writes what follows the last row (EXR's offset table, PNG's end) once every row is written.
  virtual absl::Status Finish() = 0;
  /// Rows [0, rows_sent()) have been encoded and their bytes handed to the sink (as far as
  /// the codec emits them: a PNG's compressor may still hold the last few).
  virtual int rows_sent() const = 0;
};

/// Encodes rows [row_begin, row_end) of `image` with every encoder at once (one task per
/// encoder, TBB); each encoder's sink is then called from its own task.
/// @return the first encoder's failure, in the encoders' order.
absl::Status WriteRows(const std::vector<RowEncoder*>& encoders, const RenderImage& image,
                       int row_begin, int row_end);

/// EXR bytes: half-float channels R, G, B (linear), N.x, N.y, N.z (world), U (+inf where the
/// hit vossel has no colour) and A (coverage: 1 where the pixel has a colour), and a float
/// channel Z (metres, +inf no hit); RLE compression (lossless).
absl::StatusOr<std::string> EncodeExr(const RenderImage& image);
/// Deep OpenEXR bytes (multi-layer depth, §8): per pixel its surface hits front to back as
/// samples with float channels R, G, B, A (1 where the surface has colour) and Z (metres along
/// the ray); a render with one layer gives one sample per hit pixel. ZIPS compression.
absl::StatusOr<std::string> EncodeDeepExr(const RenderImage& image);
/// PNG bytes: RGBA 8-bit, sRGB transfer (geometry::LinearToSrgb8); alpha 0 where the ray hit
/// nothing (RGB black) or a vossel without colour (RGB neutral grey 128).
absl::StatusOr<std::string> EncodePng(const RenderImage& image);
/// The whole image in `format` (one RowEncoder over every row).
absl::StatusOr<std::string> Encode(ImageFormat format, const RenderImage& image);

/// The standard sRGB OETF (geometry::LinearToSrgb), as PNG renders are written.
using geometry::LinearToSrgb;

}  // namespace vasl::render

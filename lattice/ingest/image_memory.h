/// @file image_memory.h
/// @brief Internal to ingest: an OpenImageIO reader over encoded image bytes in memory, the
///        format picked from the bytes' signature (DecodeImage, DecodeRgbzImage).
#pragma once

#include <cstdint>
#include <memory>
#include <string_view>

#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>

#include "absl/status/statusor.h"

namespace vasl::ingest::internal {

/// OpenImageIO's in-memory proxy, reading only within its bytes. OpenImageIO 2.4's own
/// IOMemReader::pread takes `size − offset` bytes when a read runs past the end without checking
/// that the offset lies within the buffer, so a read that starts at or beyond the end (an EXR
/// whose offset table points there; found by fuzz_backproject_image) copies from the memory
/// after the bytes: a crash, or that memory in the decoded pixels.
class BoundedMemReader final : public OIIO::Filesystem::IOMemReader {
 public:
  using IOMemReader::IOMemReader;
  size_t read(void* buf, size_t size) override;
  /// Up to `size` bytes from `offset`; 0 at or beyond the end, or before the start.
  size_t pread(void* buf, size_t size, int64_t offset) override;
};

/// An open reader and the in-memory proxy it reads through (which must outlive it).
struct MemoryImageInput {
  std::unique_ptr<OIIO::Filesystem::IOMemReader> reader;
  std::unique_ptr<OIIO::ImageInput> in;
};

/// Opens PNG, JPEG, EXR or TIFF bytes. With `unassociated_alpha` colour is read as stored,
/// not premultiplied by an alpha channel. INVALID_ARGUMENT for an unrecognised signature or
/// bytes that do not open; EXR headers pass CheckExrHeaders first.
absl::StatusOr<MemoryImageInput> OpenImageInMemory(std::string_view bytes, bool unassociated_alpha,
                                                   int64_t max_pixels);

/// Walks every header of OpenEXR `bytes` (magic number already matched) before OpenEXR parses
/// them, reading each attribute as OpenEXR 3.1 will: each must consume exactly the size it
/// declares (OpenEXR allocates an unknown type's claimed size, and reads a channel list up to
/// its empty name whatever the size says), the data window must be non-empty and within
/// `max_pixels` (RESOURCE_EXHAUSTED), tiles no larger than the image, and the chunk offsets the
/// headers imply (every part, every MIP/RIP level) must fit in the bytes that follow. Every
/// allocation a header can cause is then bounded by the bytes sent. INVALID_ARGUMENT names the
/// first fault.
absl::Status CheckExrHeaders(std::string_view bytes, int64_t max_pixels);

}  // namespace vasl::ingest::internal

/// @file image_memory.h
/// @brief Internal to ingest: an OpenImageIO reader over encoded image bytes in memory, the
///        format picked from the bytes' signature (DecodeImage, DecodeRgbzImage).
#pragma once

#include <memory>
#include <string_view>

#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>

#include "absl/status/statusor.h"

namespace vasl::ingest::internal {

/// An open reader and the in-memory proxy it reads through (which must outlive it).
struct MemoryImageInput {
  std::unique_ptr<OIIO::Filesystem::IOMemReader> reader;
  std::unique_ptr<OIIO::ImageInput> in;
};

/// Opens PNG, JPEG, EXR or TIFF bytes. With `unassociated_alpha` colour is read as stored,
/// not premultiplied by an alpha channel. INVALID_ARGUMENT for an unrecognised signature or
/// bytes that do not open.
absl::StatusOr<MemoryImageInput> OpenImageInMemory(std::string_view bytes, bool unassociated_alpha);

}  // namespace vasl::ingest::internal

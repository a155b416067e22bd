/// @file encode.h
/// @brief Encoders of a RenderImage: multi-channel float EXR (R,G,B,Z,N.x,N.y,N.z,U) through
///        OpenEXR, and an 8-bit sRGB PNG preview through OpenImageIO (VASL-MODEL §8 outputs).
#pragma once

#include <string>

#include "absl/status/statusor.h"
#include "lattice/render/render.h"

namespace vasl::render {

/// EXR bytes: half-free float channels R, G, B (linear), Z (metres, +inf no hit),
/// N.x, N.y, N.z (world), U; ZIP compression.
absl::StatusOr<std::string> EncodeExr(const RenderImage& image);
/// PNG bytes: RGB 8-bit, sRGB transfer, no-hit pixels black.
absl::StatusOr<std::string> EncodePng(const RenderImage& image);

}  // namespace vasl::render

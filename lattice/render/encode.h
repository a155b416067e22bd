/// @file encode.h
/// @brief Encoders of a RenderImage: multi-channel float EXR (R,G,B,Z,N.x,N.y,N.z,U) through
///        OpenEXR, and an 8-bit sRGB PNG preview through OpenImageIO (VASL-MODEL §8 outputs).
#pragma once

#include <string>

#include "absl/status/statusor.h"
#include "lattice/render/render.h"

namespace vasl::render {

/// EXR bytes: float channels R, G, B (linear), Z (metres, +inf no hit), N.x, N.y, N.z
/// (world), U (+inf where the hit vossel has no colour) and A (coverage: 1 where the pixel has
/// a colour); ZIP compression.
absl::StatusOr<std::string> EncodeExr(const RenderImage& image);
/// Deep OpenEXR bytes (multi-layer depth, §8): per pixel its surface hits front to back as
/// samples with float channels R, G, B, A (1 where the surface has colour) and Z (metres along
/// the ray); a render with one layer gives one sample per hit pixel. ZIPS compression.
absl::StatusOr<std::string> EncodeDeepExr(const RenderImage& image);
/// PNG bytes: RGBA 8-bit, sRGB transfer; alpha 0 where the ray hit nothing (RGB black) or a
/// vossel without colour (RGB neutral grey 128).
absl::StatusOr<std::string> EncodePng(const RenderImage& image);

/// The standard sRGB OETF (IEC 61966-2-1): linear [0, 1] → encoded [0, 1], piecewise
/// 12.92·c below 0.0031308, else 1.055·c^(1/2.4) − 0.055. Input clamped to [0, 1]; NaN → 0.
float LinearToSrgb(float linear);

}  // namespace vasl::render

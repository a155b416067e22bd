/// @file fuzz_limits.h
/// @brief The small limits the harnesses run under, so that whatever an input claims, what the
///        code under test may allocate stays far below libFuzzer's -malloc_limit_mb.
#pragma once

#include <cstdint>

#include "lattice/engine.h"

namespace vasl::fuzz {

/// Decoded pixels one image may have (DecodeImage, DecodeRgbzImage): 128×64. With at most 16
/// channels read as float that is a 512 KiB buffer.
inline constexpr int64_t kMaxImagePixels = 128 * 64;

/// EngineLimits for fuzz_ingest_stream: a scan's buffers are at most 4096 points × 28 bytes
/// plus 4 images × 16 KiB.
inline EngineLimits FuzzEngineLimits() {
  EngineLimits limits;
  limits.max_points_per_scan = 4096;
  limits.max_panoramas_per_scan = 4;
  limits.max_image_bytes = 16 << 10;
  limits.max_image_pixels = kMaxImagePixels;
  return limits;
}

}  // namespace vasl::fuzz

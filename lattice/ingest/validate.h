/// @file validate.h
/// @brief Everything a scan must satisfy before anything of it is stored (ARCHITECTURE.md
///        "Errors and limits": bad input never changes a project).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "lattice/geometry/pose.h"
#include "lattice/ingest/scan_input.h"
#include "lattice/ingest/sources.h"

namespace vasl::ingest {

/// The client-controlled sizes a scan may reach.
struct ScanLimits {
  int64_t max_points_per_scan = 50'000'000;
  int64_t max_panoramas_per_scan = 16;
  int64_t max_image_bytes = 512ll << 20;      ///< one encoded image
  int64_t max_image_pixels = 16384ll * 8192;  ///< one decoded image
};

/// INVALID_ARGUMENT naming `what` unless the pose has a finite position and a finite unit
/// quaternion.
absl::Status ValidatePose(const geometry::Pose& pose, const std::string& what);

/// OK when `text` (a name or label a client chose) has 1..max_bytes bytes (0..max_bytes with
/// `may_be_empty`) and no control character (so that it cannot forge a log line or a listing);
/// INVALID_ARGUMENT naming `what` otherwise.
absl::Status ValidateText(const std::string& what, const std::string& text, size_t max_bytes,
                          bool may_be_empty = false);

/// Validates a scan (names, poses, finite points, intensities, divergence, panorama names,
/// modalities, sizes, 2:1 equirect images) and reads its panoramas' headers (ProbeImage),
/// which it returns in order; their pixels are decoded later, one panorama at a time, as
/// each camera's records are made (DecodePanorama). INVALID_ARGUMENT for bad input,
/// RESOURCE_EXHAUSTED above `limits`, each message naming the scan and the field.
absl::StatusOr<std::vector<ImageHeader>> ValidateScan(const ScanInput& scan, const ScanLimits& limits);

/// Decodes panorama `index` of a validated scan; its errors name the scan and the panorama
/// (INVALID_ARGUMENT: pixels that do not decode).
absl::StatusOr<LinearImage> DecodePanorama(const ScanInput& scan, size_t index,
                                           int64_t max_image_pixels);

}  // namespace vasl::ingest

/// @file calibration.h
/// @brief Calibration health of one (LiDAR, camera) pair of a scan (VASL-MODEL §2.3): what the
///        ingest found (lattice/ingest/calibration.h) and the catalog keeps with the camera.
#pragma once

#include <cstdint>
#include <string>

namespace vasl::records {

/// The §2.3 figures of one camera against its scan's LiDAR.
struct CalibrationHealth {
  enum class Verdict : int8_t {
    kUnchecked = 0,  ///< too little to go on (no texture, too few matches): see `note`
    kOk = 1,         ///< the camera sits on its pose within the check's resolution
    kFlagged = 2,    ///< the camera's image is off where its pose projects the LiDAR
  };
  int32_t lidar_source = 0;     ///< source id of the LiDAR the camera was checked against
  int64_t points_in_view = 0;   ///< LiDAR returns the camera sees (in front, on the image)
  int64_t features = 0;         ///< textured LiDAR patches tried
  int64_t matched = 0;          ///< of those, found in the camera image (NCC, both ways)
  double cell_px = 1.0;         ///< camera pixels per analysis cell: the check's resolution
  double pixel_mean_px = 0.0;   ///< |matched − projected|, camera pixels, over the matches
  double pixel_p95_px = 0.0;    ///< its 95th percentile
  double offset_mean_m = 0.0;   ///< |x − x''|, x'' lifted at the matched pixel with range r
  double offset_p95_m = 0.0;
  double roundtrip_mean_m = 0.0;  ///< |x − x'|, x' lifted at x's own projection with range r
  double roundtrip_p95_m = 0.0;
  double rotation_deg = 0.0;    ///< the rotation that best takes projections onto matches
  Verdict verdict = Verdict::kUnchecked;
  std::string note;             ///< the verdict in words (why unchecked, what is off)
};

/// "ok", "flagged" or "unchecked".
inline const char* VerdictName(CalibrationHealth::Verdict v) {
  switch (v) {
    case CalibrationHealth::Verdict::kOk: return "ok";
    case CalibrationHealth::Verdict::kFlagged: return "flagged";
    default: return "unchecked";
  }
}

}  // namespace vasl::records

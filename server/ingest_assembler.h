/// @file ingest_assembler.h
/// @brief Reassembles an IngestScan client stream (header, points chunks, image chunks) into a
///        lattice ScanInput, rejecting any malformed stream before the engine sees it.
/// @details Stream rules (vasl.proto, IngestScan): exactly one ScanHeader, first; then
///          PointsChunk messages (16 bytes per point: little-endian float32 x, y, z, intensity,
///          sensor frame); then ImageChunk messages of the panoramas the header declared. Byte
///          totals must equal the header's (16 · lidar.point_count; encoded_size_bytes per
///          panorama). Violations are INVALID_ARGUMENT; sizes above the engine limits are
///          RESOURCE_EXHAUSTED, detected from the header so that nothing large is buffered.
///          Content checks (finite points, decodable images) are the engine's: it validates
///          fully before storing anything.
/// @warning Not thread-safe: one assembler per stream, fed in order.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "lattice/engine.h"
#include "vasl/v1/vasl.pb.h"

namespace vasl::server {

class IngestAssembler {
 public:
  explicit IngestAssembler(const EngineLimits& limits);

  /// Adds the next message of the stream; the first error is final (later calls repeat it).
  absl::Status Add(const v1::IngestScanRequest& request);
  /// Ends the stream: checks completeness and returns the scan (consumes the buffers).
  absl::StatusOr<ScanInput> Finish();

  bool has_header() const { return has_header_; }
  /// Project and scan id of the header (empty before it).
  const std::string& project() const { return project_; }
  const std::string& scan_name() const { return scan_.scan_name; }
  /// Payload bytes received so far (points + images).
  int64_t received_bytes() const { return received_bytes_; }
  /// Points announced by the header.
  int64_t point_count() const { return point_count_; }

 private:
  absl::Status AddHeader(const v1::ScanHeader& header);
  absl::Status AddPoints(const v1::PointsChunk& chunk);
  absl::Status AddImage(const v1::ImageChunk& chunk);

  EngineLimits limits_;
  absl::Status error_;
  int64_t message_index_ = 0;  ///< 1-based index of the message being added
  bool has_header_ = false;
  bool images_started_ = false;
  std::string project_;
  int64_t point_count_ = 0;
  int64_t bytes_per_point_ = 16;             ///< 16 (XYZI) or 28 (XYZIRGB), + 8 with a grid
  int64_t received_bytes_ = 0;
  std::string point_bytes_;                  ///< packed float32 LE (x, y, z, intensity[, r, g, b])
  std::vector<int64_t> expected_image_bytes_;  ///< per panorama
  std::vector<int64_t> expected_mask_bytes_;   ///< per panorama; 0: no mask
  ScanInput scan_;                           ///< header fields; panoramas receive image bytes
};

/// Unpacks little-endian float32 point records into `lidar`'s arrays (parallel for large
/// inputs): 16 bytes (x, y, z, intensity), or with `colour` 28 (x, y, z, intensity, r, g, b);
/// with `lidar->grid_columns` > 0, each followed by its row and column (uint32, 8 bytes) that
/// become its grid cell (a column beyond the grid becomes a cell beyond it, which ValidateScan
/// refuses). `bytes.size()` must be a multiple of the record size.
void UnpackPointsF32Le(std::string_view bytes, bool colour, LidarData* lidar);

}  // namespace vasl::server

/// @file ingest_assembler.cc
/// @brief IngestScan stream -> ScanInput, with structural validation.
#include "server/ingest_assembler.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <set>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include "absl/strings/str_cat.h"
#include "server/convert.h"

namespace vasl::server {
namespace {

const char* PayloadName(const v1::IngestScanRequest& request) {
  switch (request.payload_case()) {
    case v1::IngestScanRequest::kHeader: return "a ScanHeader";
    case v1::IngestScanRequest::kPoints: return "a PointsChunk";
    case v1::IngestScanRequest::kImage: return "an ImageChunk";
    default: return "an empty or unknown message";
  }
}

float LoadF32Le(const unsigned char* p) {
  const uint32_t bits = static_cast<uint32_t>(p[0]) | (static_cast<uint32_t>(p[1]) << 8) |
                        (static_cast<uint32_t>(p[2]) << 16) | (static_cast<uint32_t>(p[3]) << 24);
  float value;
  std::memcpy(&value, &bits, sizeof(value));
  return value;
}

}  // namespace

void UnpackPointsF32Le(std::string_view bytes, bool colour, LidarData* lidar) {
  const size_t record = colour ? 28 : 16;
  const bool grid = lidar->grid_columns > 0;
  const size_t stride = record + (grid ? 8 : 0);
  const size_t n = bytes.size() / stride;
  lidar->xyz_sensor_m.resize(3 * n);
  lidar->intensity.resize(n);
  lidar->rgb.resize(colour ? 3 * n : 0);
  lidar->grid_cell.resize(grid ? n : 0);
  uint32_t* cell = lidar->grid_cell.data();
  const uint64_t columns = uint64_t(std::max(0, lidar->grid_columns));
  const auto* src = reinterpret_cast<const unsigned char*>(bytes.data());
  float* xyz = lidar->xyz_sensor_m.data();
  float* intensity = lidar->intensity.data();
  float* rgb = lidar->rgb.data();
  tbb::parallel_for(tbb::blocked_range<size_t>(0, n, 1 << 16),
                    [&](const tbb::blocked_range<size_t>& r) {
                      for (size_t i = r.begin(); i != r.end(); ++i) {
                        const unsigned char* p = src + i * stride;
                        xyz[3 * i + 0] = LoadF32Le(p);
                        xyz[3 * i + 1] = LoadF32Le(p + 4);
                        xyz[3 * i + 2] = LoadF32Le(p + 8);
                        intensity[i] = LoadF32Le(p + 12);
                        if (colour) {
                          for (int c = 0; c < 3; ++c) rgb[3 * i + c] = LoadF32Le(p + 16 + 4 * c);
                        }
                        if (grid) {
                          uint32_t rc[2];
                          std::memcpy(rc, p + record, 8);  // little-endian hosts only (x86, arm)
                          const uint64_t at = rc[1] < columns ? rc[0] * columns + rc[1]
                                                              : ~uint64_t(0);
                          cell[i] = at > 0xffffffffu ? 0xffffffffu : uint32_t(at);
                        }
                      }
                    });
}

IngestAssembler::IngestAssembler(const EngineLimits& limits) : limits_(limits) {}

absl::Status IngestAssembler::Add(const v1::IngestScanRequest& request) {
  if (!error_.ok()) return error_;
  ++message_index_;
  absl::Status status;
  if (!has_header_ && request.payload_case() != v1::IngestScanRequest::kHeader) {
    status = absl::InvalidArgumentError(absl::StrCat(
        "the ingest stream must start with a ScanHeader, but message ", message_index_, " is ",
        PayloadName(request), "; send the header (project, scan, pose, lidar, panoramas) first"));
  } else {
    switch (request.payload_case()) {
      case v1::IngestScanRequest::kHeader: status = AddHeader(request.header()); break;
      case v1::IngestScanRequest::kPoints: status = AddPoints(request.points()); break;
      case v1::IngestScanRequest::kImage: status = AddImage(request.image()); break;
      default:
        status = absl::InvalidArgumentError(absl::StrCat(
            "message ", message_index_,
            " of the ingest stream has no known payload; expected header, points or image "
            "(is the client newer than the server?)"));
    }
  }
  error_ = status;
  return status;
}

absl::Status IngestAssembler::AddHeader(const v1::ScanHeader& header) {
  if (has_header_) {
    return absl::InvalidArgumentError(absl::StrCat(
        "message ", message_index_, " is a second ScanHeader; send exactly one header, first"));
  }
  if (header.project().empty()) {
    return absl::InvalidArgumentError("header.project is empty: name the project to ingest into");
  }
  if (header.scan().empty()) {
    return absl::InvalidArgumentError(
        "header.scan is empty: give the scan an id unique in the project");
  }
  if (!header.has_pose()) {
    return absl::InvalidArgumentError("header.pose is required: the scanner's pose in the world");
  }
  absl::StatusOr<geometry::Pose> pose = PoseFromProto(header.pose(), "header.pose");
  if (!pose.ok()) return pose.status();
  std::string captured;
  if (header.has_capture_time()) {
    absl::StatusOr<std::string> iso = TimestampToIso(header.capture_time(), "header.capture_time");
    if (!iso.ok()) return iso.status();
    captured = *iso;
  }
  const v1::LidarModel& lidar = header.lidar();  // unset or no points: a camera-only scan
  const bool camera_only = lidar.point_count() == 0;
  const bool cameras = std::any_of(header.panoramas().begin(), header.panoramas().end(),
                                   [](const v1::PanoramaDescriptor& p) { return !p.visual_reference(); });
  if (camera_only && !cameras) {
    return absl::InvalidArgumentError(
        "the header declares no LiDAR points (header.lidar.point_count) and no camera images "
        "(header.panoramas; visual references alone colour nothing): a scan needs one or the "
        "other");
  }
  if (!camera_only &&
      (!std::isfinite(lidar.divergence_rad()) || lidar.divergence_rad() <= 0.0)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "header.lidar.divergence_rad must be > 0 radians (e.g. 0.0003), got ",
        lidar.divergence_rad()));
  }
  switch (lidar.point_format()) {
    case v1::POINT_FORMAT_UNSPECIFIED:
    case v1::POINT_FORMAT_XYZI_F32LE: bytes_per_point_ = 16; break;
    case v1::POINT_FORMAT_XYZIRGB_F32LE: bytes_per_point_ = 28; break;
    default:
      return absl::InvalidArgumentError(absl::StrCat(
          "header.lidar.point_format ", static_cast<int>(lidar.point_format()),
          " is not supported; use POINT_FORMAT_XYZI_F32LE (16 bytes per point) or "
          "POINT_FORMAT_XYZIRGB_F32LE (28)"));
  }
  if (lidar.has_grid()) {
    if (camera_only) {
      return absl::InvalidArgumentError("header.lidar.grid is set but the scan has no points");
    }
    if (lidar.grid().rows() <= 0 || lidar.grid().columns() <= 0) {
      return absl::InvalidArgumentError(absl::StrCat(
          "header.lidar.grid must have rows and columns > 0, got ", lidar.grid().rows(), "x",
          lidar.grid().columns()));
    }
    bytes_per_point_ += 8;  // row, column
    scan_.lidar.grid_rows = lidar.grid().rows();
    scan_.lidar.grid_columns = lidar.grid().columns();
  }
  if (lidar.point_count() < 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        "header.lidar.point_count must be >= 0 (the number of points that follow), got ",
        lidar.point_count()));
  }
  if (lidar.point_count() > limits_.max_points_per_scan) {
    return absl::ResourceExhaustedError(
        absl::StrCat("header.lidar.point_count ", lidar.point_count(),
                     " exceeds the server's limit of ", limits_.max_points_per_scan,
                     " points per scan; split the scan"));
  }
  if (header.panoramas_size() > limits_.max_panoramas_per_scan) {
    return absl::ResourceExhaustedError(
        absl::StrCat("header has ", header.panoramas_size(), " panoramas; the limit is ",
                     limits_.max_panoramas_per_scan, " per scan"));
  }
  std::set<std::string> names;
  for (int i = 0; i < header.panoramas_size(); ++i) {
    const v1::PanoramaDescriptor& pano = header.panoramas(i);
    const std::string field = absl::StrCat("header.panoramas[", i, "]");
    if (pano.name().empty()) {
      return absl::InvalidArgumentError(absl::StrCat(field, ".name is empty"));
    }
    if (!names.insert(pano.name()).second) {
      return absl::InvalidArgumentError(
          absl::StrCat(field, ".name \"", pano.name(), "\" is used twice in the scan"));
    }
    absl::StatusOr<records::Modality> modality =
        pano.visual_reference() ? records::Modality::kRgb  // no source: its modality is moot
                                : PanoramaModalityFromProto(pano.modality(), field);
    if (!modality.ok()) return modality.status();
    if (!pano.has_pose()) {
      return absl::InvalidArgumentError(absl::StrCat(field, ".pose is required"));
    }
    absl::StatusOr<geometry::Pose> pano_pose = PoseFromProto(pano.pose(), field + ".pose");
    if (!pano_pose.ok()) return pano_pose.status();
    if (!std::isfinite(pano.angular_resolution_rad()) || pano.angular_resolution_rad() < 0.0) {
      return absl::InvalidArgumentError(
          absl::StrCat(field, ".angular_resolution_rad must be >= 0 (0: from the image), got ",
                       pano.angular_resolution_rad()));
    }
    if (pano.encoded_size_bytes() <= 0) {
      return absl::InvalidArgumentError(
          absl::StrCat(field, ".encoded_size_bytes must be > 0 (the size of the image file)"));
    }
    if (pano.encoded_size_bytes() > limits_.max_image_bytes) {
      return absl::ResourceExhaustedError(
          absl::StrCat(field, ".encoded_size_bytes ", pano.encoded_size_bytes(),
                       " exceeds the server's limit of ", limits_.max_image_bytes, " bytes"));
    }
    if (pano.mask_size_bytes() < 0 || pano.mask_size_bytes() > limits_.max_image_bytes) {
      return absl::Status(
          pano.mask_size_bytes() < 0 ? absl::StatusCode::kInvalidArgument
                                     : absl::StatusCode::kResourceExhausted,
          absl::StrCat(field, ".mask_size_bytes ", pano.mask_size_bytes(),
                       " must lie in [0, ", limits_.max_image_bytes, "] (0: no mask)"));
    }
    PanoramaData data;
    data.name = pano.name();
    data.pose = *pano_pose;
    data.modality = *modality;
    data.angular_resolution_rad = pano.angular_resolution_rad();
    if (pano.has_pinhole() && !pano.visual_reference()) {
      absl::StatusOr<geometry::PinholeIntrinsics> k =
          PinholeFromProto(pano.pinhole(), absl::StrCat(field, ".pinhole"));
      if (!k.ok()) return k.status();
      data.pinhole = *k;
    }
    if (pano.has_sphere() && !pano.visual_reference()) {
      data.sphere = ingest::SphereWindow{pano.sphere().width_px(), pano.sphere().height_px(),
                                         pano.sphere().left_px(), pano.sphere().top_px()};
    }
    if (pano.has_cylinder() && !pano.visual_reference()) {
      data.cylinder = ingest::CylinderImage{pano.cylinder().pixel_width_rad(),
                                            pano.cylinder().pixel_height_m(),
                                            pano.cylinder().radius_m(),
                                            pano.cylinder().principal_y_px()};
    }
    data.visual_reference = pano.visual_reference();
    scan_.panoramas.push_back(std::move(data));
    expected_image_bytes_.push_back(pano.encoded_size_bytes());
    expected_mask_bytes_.push_back(pano.mask_size_bytes());
  }
  has_header_ = true;
  project_ = header.project();
  scan_.scan_name = header.scan();
  scan_.rig = header.rig();
  scan_.captured_utc = captured;
  scan_.pose = *pose;
  scan_.lidar.divergence_rad = lidar.divergence_rad();
  point_count_ = lidar.point_count();
  // Nothing is reserved for what the header declares: memory follows the bytes that arrive
  // (the service also bounds the bytes all streams hold, --max-inflight-ingest-bytes).
  return absl::OkStatus();
}

absl::Status IngestAssembler::AddPoints(const v1::PointsChunk& chunk) {
  if (images_started_) {
    return absl::InvalidArgumentError(absl::StrCat(
        "message ", message_index_,
        " is a PointsChunk after an ImageChunk; send all points before the images"));
  }
  const int64_t size = static_cast<int64_t>(chunk.data().size());
  if (size % bytes_per_point_ != 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        "message ", message_index_, ": a PointsChunk of ", size, " bytes is not a multiple of ",
        bytes_per_point_, " (per point float32 x, y, z, intensity",
        bytes_per_point_ - (scan_.lidar.grid_columns > 0 ? 8 : 0) == 28 ? ", r, g, b" : "",
        scan_.lidar.grid_columns > 0 ? ", then uint32 row, column)" : ")"));
  }
  const int64_t total = static_cast<int64_t>(point_bytes_.size()) + size;
  if (total > point_count_ * bytes_per_point_) {
    return absl::InvalidArgumentError(absl::StrCat(
        "the points chunks carry more than header.lidar.point_count = ", point_count_,
        " points (", total / bytes_per_point_, " so far)"));
  }
  point_bytes_.append(chunk.data());
  received_bytes_ += size;
  return absl::OkStatus();
}

absl::Status IngestAssembler::AddImage(const v1::ImageChunk& chunk) {
  images_started_ = true;
  int index = -1;
  if (!chunk.panorama_name().empty()) {
    for (size_t i = 0; i < scan_.panoramas.size(); ++i) {
      if (scan_.panoramas[i].name == chunk.panorama_name()) index = static_cast<int>(i);
    }
    if (index < 0) {
      return absl::InvalidArgumentError(absl::StrCat(
          "message ", message_index_, ": an ImageChunk for panorama \"", chunk.panorama_name(),
          "\", which the header does not declare; declare it in header.panoramas"));
    }
  } else {
    index = chunk.panorama_index();
    if (index < 0 || index >= static_cast<int>(scan_.panoramas.size())) {
      return absl::InvalidArgumentError(absl::StrCat(
          "message ", message_index_, ": an ImageChunk for panorama_index ", index,
          ", but the header declares ", scan_.panoramas.size(), " panoramas"));
    }
  }
  PanoramaData& pano = scan_.panoramas[static_cast<size_t>(index)];
  std::string& bytes = chunk.mask() ? pano.encoded_mask : pano.encoded_image;
  const int64_t expected = (chunk.mask() ? expected_mask_bytes_ : expected_image_bytes_)[
      static_cast<size_t>(index)];
  const int64_t total = static_cast<int64_t>(bytes.size() + chunk.data().size());
  if (total > expected) {
    return absl::InvalidArgumentError(absl::StrCat(
        "panorama \"", pano.name, "\": the ", chunk.mask() ? "mask" : "image",
        " chunks carry more than its ", chunk.mask() ? "mask_size_bytes" : "encoded_size_bytes",
        " = ", expected, " (", total, " so far)"));
  }
  bytes.append(chunk.data());
  received_bytes_ += static_cast<int64_t>(chunk.data().size());
  return absl::OkStatus();
}

absl::StatusOr<ScanInput> IngestAssembler::Finish() {
  if (!error_.ok()) return error_;
  if (!has_header_) {
    return absl::InvalidArgumentError(
        "the ingest stream ended without a ScanHeader; send the header first, then points, "
        "then images");
  }
  const int64_t received_points = static_cast<int64_t>(point_bytes_.size()) / bytes_per_point_;
  if (received_points != point_count_) {
    return absl::InvalidArgumentError(
        absl::StrCat("the stream carried ", received_points,
                     " points but header.lidar.point_count is ", point_count_));
  }
  for (size_t i = 0; i < scan_.panoramas.size(); ++i) {
    const int64_t got = static_cast<int64_t>(scan_.panoramas[i].encoded_image.size());
    if (got != expected_image_bytes_[i]) {
      return absl::InvalidArgumentError(absl::StrCat(
          "panorama \"", scan_.panoramas[i].name, "\": received ", got,
          " image bytes but its encoded_size_bytes is ", expected_image_bytes_[i]));
    }
    const int64_t mask = static_cast<int64_t>(scan_.panoramas[i].encoded_mask.size());
    if (mask != expected_mask_bytes_[i]) {
      return absl::InvalidArgumentError(absl::StrCat(
          "panorama \"", scan_.panoramas[i].name, "\": received ", mask,
          " mask bytes but its mask_size_bytes is ", expected_mask_bytes_[i]));
    }
  }
  UnpackPointsF32Le(point_bytes_, bytes_per_point_ - (scan_.lidar.grid_columns > 0 ? 8 : 0) == 28,
                    &scan_.lidar);
  std::string().swap(point_bytes_);
  error_ = absl::FailedPreconditionError("IngestAssembler::Finish was already called");
  return std::move(scan_);
}

}  // namespace vasl::server

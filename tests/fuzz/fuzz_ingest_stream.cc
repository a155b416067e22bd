/// @file fuzz_ingest_stream.cc
/// @brief libFuzzer harness over the IngestScan stream rules: the input is a sequence of
///        length-prefixed serialized vasl.v1.IngestScanRequest messages (tests/fuzz/frames.h),
///        fed in order to server::IngestAssembler as vasld's reactor does, then Finish and,
///        for a complete stream, the engine's ingest::ValidateScan (which decodes the
///        panoramas) under small EngineLimits (tests/fuzz/fuzz_limits.h).
/// @details Claims checked on every input, besides ASan/UBSan/LSan's:
///          - every rejection is INVALID_ARGUMENT or RESOURCE_EXHAUSTED with a message, and the
///            assembler's first error is final (a later Add and Finish repeat it);
///          - the payload buffered never exceeds what the limits allow, whatever the header
///            claims; an accepted scan has exactly header.point_count points (3 coordinates, 1
///            intensity, 0 or 3 colour values each), at most max_panoramas_per_scan panoramas of
///            at most max_image_bytes each; Finish twice is FAILED_PRECONDITION;
///          - a validated scan has one decoded image per panorama, within max_image_pixels, with
///            3 channels (RGB) or 1 (IR) and width·height·channels values.
///          A frame that does not parse ends the input: gRPC fails such a call before the
///          assembler sees it. A custom mutator (LLVMFuzzerCustomMutator) keeps the framing and
///          mutates one frame at a time: one protobuf field (tests/fuzz/proto_mutator.h), a
///          chunk split in two, a frame duplicated, dropped or swapped, or raw bytes.
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <random>
#include <string>
#include <vector>

#include <google/protobuf/stubs/logging.h>

#include "lattice/ingest/validate.h"
#include "server/ingest_assembler.h"
#include "tests/fuzz/frames.h"
#include "tests/fuzz/fuzz_check.h"
#include "tests/fuzz/fuzz_limits.h"
#include "tests/fuzz/proto_mutator.h"

extern "C" size_t LLVMFuzzerMutate(uint8_t* data, size_t size, size_t max_size);

namespace {

using vasl::EngineLimits;
using vasl::ScanInput;
using vasl::server::IngestAssembler;
using vasl::v1::IngestScanRequest;
namespace fuzz = vasl::fuzz;

/// What vasld's engine passes to ValidateScan (lattice/engine.cc, Impl::ScanLimits).
vasl::ingest::ScanLimits ToScanLimits(const EngineLimits& limits) {
  return {limits.max_points_per_scan, limits.max_panoramas_per_scan, limits.max_image_bytes,
          limits.max_image_pixels};
}

void CheckScan(const ScanInput& scan, int64_t point_count, const EngineLimits& limits) {
  const auto n = static_cast<size_t>(point_count);
  VASL_FUZZ_CHECK(point_count >= 0 && point_count <= limits.max_points_per_scan,
                  "accepted point_count ", point_count);
  // No points: a camera-only scan, which needs a camera image (a visual reference colours
  // nothing).
  const bool camera = std::any_of(scan.panoramas.begin(), scan.panoramas.end(),
                                  [](const vasl::PanoramaData& p) { return !p.visual_reference; });
  VASL_FUZZ_CHECK(point_count > 0 || camera, "a scan without points or camera images accepted");
  VASL_FUZZ_CHECK(scan.lidar.xyz_sensor_m.size() == 3 * n, scan.lidar.xyz_sensor_m.size(),
                  " coordinates for ", n, " points");
  VASL_FUZZ_CHECK(scan.lidar.intensity.size() == n, scan.lidar.intensity.size(),
                  " intensities for ", n, " points");
  VASL_FUZZ_CHECK(scan.lidar.rgb.empty() || scan.lidar.rgb.size() == 3 * n,
                  scan.lidar.rgb.size(), " colour values for ", n, " points");
  VASL_FUZZ_CHECK(static_cast<int64_t>(scan.panoramas.size()) <= limits.max_panoramas_per_scan,
                  scan.panoramas.size(), " panoramas accepted");
  for (const vasl::PanoramaData& pano : scan.panoramas) {
    VASL_FUZZ_CHECK(!pano.encoded_image.empty() &&
                        static_cast<int64_t>(pano.encoded_image.size()) <= limits.max_image_bytes,
                    "panorama '", pano.name, "' accepted with ", pano.encoded_image.size(),
                    " bytes");
  }
}

/// What ValidateScan read of the panoramas' headers, and what each decodes to (as an ingest
/// decodes them, one at a time): within the limits, the channels of its modality, every value.
void CheckImages(const ScanInput& scan, const std::vector<vasl::ingest::ImageHeader>& headers,
                 const EngineLimits& limits) {
  VASL_FUZZ_CHECK(headers.size() == scan.panoramas.size(), headers.size(), " headers for ",
                  scan.panoramas.size(), " panoramas");
  for (size_t i = 0; i < headers.size(); ++i) {
    const vasl::ingest::ImageHeader& header = headers[i];
    VASL_FUZZ_CHECK(header.width_px > 0 && header.height_px > 0 &&
                        int64_t{header.width_px} * header.height_px <= limits.max_image_pixels,
                    "header ", i, " says ", header.width_px, "x", header.height_px);
    const absl::StatusOr<vasl::ingest::LinearImage> decoded =
        vasl::ingest::DecodePanorama(scan, i, limits.max_image_pixels);
    if (!decoded.ok()) {  // a header that reads may still head pixels that do not
      fuzz::CheckRejection(decoded.status(), "DecodePanorama");
      continue;
    }
    const vasl::ingest::LinearImage& im = *decoded;
    const int want_channels = scan.panoramas[i].modality == vasl::records::Modality::kIr ? 1 : 3;
    VASL_FUZZ_CHECK(im.width_px == header.width_px && im.height_px == header.height_px,
                    "image ", i, " is ", im.width_px, "x", im.height_px, ", its header said ",
                    header.width_px, "x", header.height_px);
    VASL_FUZZ_CHECK(im.channels == want_channels, "image ", i, " has ", im.channels,
                    " channels");
    VASL_FUZZ_CHECK(im.pixels.size() == size_t(im.width_px) * size_t(im.height_px) * size_t(im.channels),
                    "image ", i, " has ", im.pixels.size(), " values");
  }
}

}  // namespace

extern "C" int LLVMFuzzerInitialize(int* /*argc*/, char*** /*argv*/) {
  // Invalid UTF-8 in string fields is expected input: keep protobuf's parse errors quiet.
  google::protobuf::SetLogHandler(nullptr);
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const EngineLimits limits = fuzz::FuzzEngineLimits();
  const int64_t max_payload_bytes =
      limits.max_points_per_scan * 28 + limits.max_panoramas_per_scan * limits.max_image_bytes;
  IngestAssembler assembler(limits);
  for (std::string_view frame :
       fuzz::DecodeFrames(std::string_view(reinterpret_cast<const char*>(data), size))) {
    IngestScanRequest request;
    if (!request.ParseFromArray(frame.data(), static_cast<int>(frame.size()))) return 0;
    const absl::Status status = assembler.Add(request);
    VASL_FUZZ_CHECK(assembler.received_bytes() <= max_payload_bytes, "buffered ",
                    assembler.received_bytes(), " payload bytes");
    VASL_FUZZ_CHECK(assembler.point_count() <= limits.max_points_per_scan, "point_count ",
                    assembler.point_count(), " accepted");
    if (!status.ok()) {
      fuzz::CheckRejection(status, "IngestAssembler::Add");
      const absl::Status again = assembler.Add(request);
      VASL_FUZZ_CHECK(again == status, "a later Add returned ", again.ToString(),
                      " after ", status.ToString());
      const absl::StatusOr<ScanInput> finished = assembler.Finish();
      VASL_FUZZ_CHECK(!finished.ok() && finished.status() == status,
                      "Finish after a failed Add returned ", finished.status().ToString());
      return 0;
    }
  }
  absl::StatusOr<ScanInput> scan = assembler.Finish();
  if (!scan.ok()) {
    fuzz::CheckRejection(scan.status(), "IngestAssembler::Finish");
    return 0;
  }
  VASL_FUZZ_CHECK(assembler.Finish().status().code() == absl::StatusCode::kFailedPrecondition,
                  "a second Finish did not fail");
  CheckScan(*scan, assembler.point_count(), limits);
  absl::StatusOr<std::vector<vasl::ingest::ImageHeader>> headers =
      vasl::ingest::ValidateScan(*scan, ToScanLimits(limits));
  if (!headers.ok()) {
    fuzz::CheckRejection(headers.status(), "ValidateScan");
    return 0;
  }
  CheckImages(*scan, *headers, limits);
  return 0;
}

extern "C" size_t LLVMFuzzerCustomMutator(uint8_t* data, size_t size, size_t max_size,
                                          unsigned int seed) {
  std::minstd_rand rng(seed);
  const std::vector<std::string_view> views =
      fuzz::DecodeFrames(std::string_view(reinterpret_cast<const char*>(data), size));
  if (views.empty() || rng() % 8 == 0) return LLVMFuzzerMutate(data, size, max_size);
  std::vector<std::string> frames(views.begin(), views.end());
  const size_t growth = max_size > size ? std::min<size_t>(max_size - size, 4096) : 0;
  const auto mutate_bytes = [](uint8_t* d, size_t s, size_t m) { return LLVMFuzzerMutate(d, s, m); };
  const size_t i = rng() % frames.size();
  switch (rng() % 8) {
    case 0:  // duplicate a frame (a second header, a repeated chunk)
      if (frames.size() < fuzz::kMaxFrames) {
        std::string copy = frames[i];
        frames.insert(frames.begin() + static_cast<std::ptrdiff_t>(rng() % (frames.size() + 1)),
                      std::move(copy));
      }
      break;
    case 1:  // drop a frame
      if (frames.size() > 1) frames.erase(frames.begin() + static_cast<std::ptrdiff_t>(i));
      break;
    case 2:  // swap two frames (order rules)
      std::swap(frames[i], frames[rng() % frames.size()]);
      break;
    case 3: {  // split a points or image chunk in two (byte totals over several chunks)
      IngestScanRequest request;
      if (frames.size() >= fuzz::kMaxFrames || !request.ParseFromString(frames[i])) break;
      std::string* chunk = request.has_points()  ? request.mutable_points()->mutable_data()
                           : request.has_image() ? request.mutable_image()->mutable_data()
                                                 : nullptr;
      if (chunk == nullptr || chunk->size() < 2) break;
      size_t at = 1 + rng() % (chunk->size() - 1);
      if (request.has_points() && rng() % 2 == 0) at = (at / 16) * 16;
      IngestScanRequest tail = request;
      *(request.has_points() ? tail.mutable_points()->mutable_data()
                             : tail.mutable_image()->mutable_data()) = chunk->substr(at);
      chunk->resize(at);
      frames[i] = request.SerializeAsString();
      frames.insert(frames.begin() + static_cast<std::ptrdiff_t>(i) + 1, tail.SerializeAsString());
      break;
    }
    case 4: {  // raw bytes of one frame
      std::string& f = frames[i];
      const size_t old = f.size();
      f.resize(old + growth);
      f.resize(LLVMFuzzerMutate(reinterpret_cast<uint8_t*>(f.data()), old, f.size()));
      break;
    }
    default: {  // one field of one message
      IngestScanRequest request;
      if (!request.ParseFromString(frames[i])) break;
      fuzz::MutateMessage(&request, rng, mutate_bytes, growth);
      frames[i] = request.SerializeAsString();
      break;
    }
  }
  const std::string out = fuzz::EncodeFrames(frames);
  if (out.empty() || out.size() > max_size) return LLVMFuzzerMutate(data, size, max_size);
  std::memcpy(data, out.data(), out.size());
  return out.size();
}

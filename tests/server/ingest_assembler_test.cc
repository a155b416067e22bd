/// @file ingest_assembler_test.cc
/// @brief The IngestScan stream rules (vasl.proto): header first and once, 16-byte points (28
///        with colour), image chunks only for declared panoramas, byte totals equal to the
///        header's; limits are RESOURCE_EXHAUSTED. A well-formed stream reassembles
///        bit-exactly.
#include "server/ingest_assembler.h"

#include <cmath>
#include <cstdio>
#include <cstring>
#include <random>
#include <string>
#include <vector>

#include <gtest/gtest.h>

namespace vasl::server {
namespace {

std::string PackPoints(const std::vector<float>& xyzi) {
  std::string bytes;
  for (float f : xyzi) {
    uint32_t bits;
    std::memcpy(&bits, &f, 4);
    for (int b = 0; b < 4; ++b) bytes.push_back(static_cast<char>((bits >> (8 * b)) & 0xff));
  }
  return bytes;
}

v1::IngestScanRequest Header(int64_t points, int64_t image_bytes) {
  v1::IngestScanRequest r;
  v1::ScanHeader* h = r.mutable_header();
  h->set_project("demo");
  h->set_scan("scan-1");
  h->set_rig("test-rig");
  h->mutable_pose()->mutable_position_m()->set_z(1.5);
  h->mutable_pose()->mutable_quaternion_xyzw()->set_w(1.0);
  h->mutable_lidar()->set_divergence_rad(3e-4);
  h->mutable_lidar()->set_point_format(v1::POINT_FORMAT_XYZI_F32LE);
  h->mutable_lidar()->set_point_count(points);
  v1::PanoramaDescriptor* p = h->add_panoramas();
  p->set_name("cam0");
  p->set_modality(v1::MODALITY_RGB);
  p->mutable_pose()->mutable_quaternion_xyzw()->set_w(2.0);  // normalised by the server
  p->set_encoded_size_bytes(image_bytes);
  return r;
}

v1::IngestScanRequest Points(const std::string& bytes) {
  v1::IngestScanRequest r;
  r.mutable_points()->set_data(bytes);
  return r;
}

v1::IngestScanRequest Image(const std::string& name, const std::string& bytes) {
  v1::IngestScanRequest r;
  r.mutable_image()->set_panorama_name(name);
  r.mutable_image()->set_data(bytes);
  return r;
}

TEST(IngestAssemblerTest, WellFormedStreamReassemblesExactly) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> u(-10.f, 10.f);
  const int n = 1000;
  std::vector<float> xyzi(4 * n);
  for (float& f : xyzi) f = u(rng);
  const std::string bytes = PackPoints(xyzi);
  const std::string image = "not-decoded-here";
  IngestAssembler a(EngineLimits{});
  ASSERT_TRUE(a.Add(Header(n, static_cast<int64_t>(image.size()))).ok());
  // Points in three uneven chunks (multiples of 16).
  ASSERT_TRUE(a.Add(Points(bytes.substr(0, 16 * 100))).ok());
  ASSERT_TRUE(a.Add(Points(bytes.substr(16 * 100, 16 * 650))).ok());
  ASSERT_TRUE(a.Add(Points(bytes.substr(16 * 750))).ok());
  ASSERT_TRUE(a.Add(Image("cam0", image.substr(0, 5))).ok());
  v1::IngestScanRequest by_index;
  by_index.mutable_image()->set_panorama_index(0);
  by_index.mutable_image()->set_data(image.substr(5));
  ASSERT_TRUE(a.Add(by_index).ok());
  absl::StatusOr<ScanInput> scan = a.Finish();
  ASSERT_TRUE(scan.ok()) << scan.status();
  ASSERT_EQ(scan->lidar.xyz_sensor_m.size(), 3u * n);
  ASSERT_EQ(scan->lidar.intensity.size(), static_cast<size_t>(n));
  int mismatches = 0;
  for (int i = 0; i < n; ++i) {
    for (int c = 0; c < 3; ++c) {
      mismatches += scan->lidar.xyz_sensor_m[3 * i + c] != xyzi[4 * i + c];
    }
    mismatches += scan->lidar.intensity[i] != xyzi[4 * i + 3];
  }
  EXPECT_EQ(mismatches, 0);
  EXPECT_EQ(scan->scan_name, "scan-1");
  EXPECT_DOUBLE_EQ(scan->lidar.divergence_rad, 3e-4);
  EXPECT_DOUBLE_EQ(scan->pose.o_world.z(), 1.5);
  ASSERT_EQ(scan->panoramas.size(), 1u);
  EXPECT_EQ(scan->panoramas[0].encoded_image, image);
  EXPECT_NEAR(scan->panoramas[0].pose.q_world_sensor.norm(), 1.0, 1e-12);
  EXPECT_EQ(a.received_bytes(), static_cast<int64_t>(bytes.size() + image.size()));
  std::printf("reassembled %d points (%zu bytes) and %zu image bytes, %d mismatches\n", n,
              bytes.size(), image.size(), mismatches);
}

absl::StatusCode FirstError(const std::vector<v1::IngestScanRequest>& stream,
                            std::string* message) {
  IngestAssembler a(EngineLimits{});
  for (const auto& r : stream) {
    absl::Status s = a.Add(r);
    if (!s.ok()) {
      *message = std::string(s.message());
      return s.code();
    }
  }
  absl::StatusOr<ScanInput> scan = a.Finish();
  *message = std::string(scan.status().message());
  return scan.status().code();
}

// Claim: POINT_FORMAT_XYZIRGB_F32LE points (28 bytes: x, y, z, intensity, r, g, b) reassemble
// bit-exactly with their colour, and a chunk that is not whole 28-byte points is refused.
TEST(IngestAssemblerTest, ColouredPointsReassembleWithTheirColour) {
  const std::vector<float> xyzirgb = {1.0f, 2.0f, 3.0f, 0.5f, 0.25f, 0.125f, 1.0f,
                                      -4.0f, 5.5f, 0.0f, 0.75f, 0.0f, 0.5f, 0.0625f};
  const std::string pts = PackPoints(xyzirgb);
  v1::IngestScanRequest header = Header(2, 3);
  header.mutable_header()->mutable_lidar()->set_point_format(v1::POINT_FORMAT_XYZIRGB_F32LE);
  IngestAssembler a(EngineLimits{});
  ASSERT_TRUE(a.Add(header).ok());
  ASSERT_TRUE(a.Add(Points(pts.substr(0, 28))).ok());
  ASSERT_TRUE(a.Add(Points(pts.substr(28))).ok());
  ASSERT_TRUE(a.Add(Image("cam0", "abc")).ok());
  auto scan = a.Finish();
  ASSERT_TRUE(scan.ok()) << scan.status();
  ASSERT_EQ(scan->lidar.xyz_sensor_m.size(), 6u);
  ASSERT_EQ(scan->lidar.rgb.size(), 6u);
  for (int i = 0; i < 2; ++i) {
    for (int c = 0; c < 3; ++c) {
      EXPECT_EQ(scan->lidar.xyz_sensor_m[3 * i + c], xyzirgb[7 * i + c]);
      EXPECT_EQ(scan->lidar.rgb[3 * i + c], xyzirgb[7 * i + 4 + c]);
    }
    EXPECT_EQ(scan->lidar.intensity[i], xyzirgb[7 * i + 3]);
  }
  IngestAssembler b(EngineLimits{});
  ASSERT_TRUE(b.Add(header).ok());
  const absl::Status partial = b.Add(Points(pts.substr(0, 16)));
  EXPECT_EQ(partial.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(partial.message().find("not a multiple of 28"), std::string::npos) << partial;
}

TEST(IngestAssemblerTest, MalformedStreamsAreInvalidArgument) {
  const std::string pts = PackPoints({1, 2, 3, 4, 5, 6, 7, 8});  // 2 points
  struct Case {
    const char* what;
    std::vector<v1::IngestScanRequest> stream;
    const char* needle;
  };
  v1::IngestScanRequest empty_msg;
  v1::IngestScanRequest nan_pose = Header(2, 3);
  nan_pose.mutable_header()->mutable_pose()->mutable_position_m()->set_x(std::nan(""));
  v1::IngestScanRequest zero_quat = Header(2, 3);
  zero_quat.mutable_header()->mutable_pose()->mutable_quaternion_xyzw()->set_w(0.0);
  v1::IngestScanRequest no_pose = Header(2, 3);
  no_pose.mutable_header()->clear_pose();
  v1::IngestScanRequest bad_modality = Header(2, 3);
  bad_modality.mutable_header()->mutable_panoramas(0)->set_modality(v1::MODALITY_LIDAR);
  v1::IngestScanRequest bad_index;
  bad_index.mutable_image()->set_panorama_index(3);
  bad_index.mutable_image()->set_data("abc");
  const std::vector<Case> cases = {
      {"empty stream", {}, "without a ScanHeader"},
      {"points before header", {Points(pts), Header(2, 3)}, "must start with a ScanHeader"},
      {"two headers", {Header(2, 3), Header(2, 3)}, "second ScanHeader"},
      {"message without payload", {Header(2, 3), empty_msg}, "no known payload"},
      {"chunk of 17 bytes", {Header(2, 3), Points(pts.substr(0, 17))}, "not a multiple of 16"},
      {"more points than declared", {Header(1, 3), Points(pts)}, "more than header.lidar"},
      {"fewer points than declared", {Header(3, 3), Points(pts), Image("cam0", "abc")},
       "carried 2 points"},
      {"image for undeclared panorama", {Header(2, 3), Points(pts), Image("cam9", "abc")},
       "does not declare"},
      {"image index out of range", {Header(2, 3), Points(pts), bad_index}, "declares 1"},
      {"image too long", {Header(2, 3), Points(pts), Image("cam0", "abcd")}, "more than its"},
      {"image too short", {Header(2, 3), Points(pts), Image("cam0", "ab")}, "received 2"},
      {"points after image", {Header(4, 3), Points(pts), Image("cam0", "abc"), Points(pts)},
       "after an ImageChunk"},
      {"NaN in pose", {nan_pose}, "must be finite"},
      {"zero quaternion", {zero_quat}, "quaternion"},
      {"no pose", {no_pose}, "pose is required"},
      {"LiDAR modality for a panorama", {bad_modality}, "MODALITY_RGB or MODALITY_IR"},
  };
  for (const Case& c : cases) {
    std::string message;
    const absl::StatusCode code = FirstError(c.stream, &message);
    EXPECT_EQ(code, absl::StatusCode::kInvalidArgument) << c.what << ": " << message;
    EXPECT_NE(message.find(c.needle), std::string::npos) << c.what << ": " << message;
    std::printf("%-32s -> %s: %s\n", c.what, absl::StatusCodeToString(code).c_str(),
                message.c_str());
  }
}

TEST(IngestAssemblerTest, SizesAboveLimitsAreResourceExhausted) {
  EngineLimits limits;
  limits.max_points_per_scan = 10;
  limits.max_image_bytes = 100;
  {
    IngestAssembler a(limits);
    absl::Status s = a.Add(Header(11, 3));
    EXPECT_EQ(s.code(), absl::StatusCode::kResourceExhausted) << s;
  }
  {
    IngestAssembler a(limits);
    absl::Status s = a.Add(Header(10, 101));
    EXPECT_EQ(s.code(), absl::StatusCode::kResourceExhausted) << s;
  }
  {
    IngestAssembler a(limits);
    EXPECT_TRUE(a.Add(Header(10, 100)).ok());
  }
}

}  // namespace
}  // namespace vasl::server

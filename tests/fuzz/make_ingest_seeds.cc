/// @file make_ingest_seeds.cc
/// @brief vasl_fuzz_seeds: writes the seed corpus of fuzz_ingest_stream, well-formed IngestScan
///        streams in the harness's framing (tests/fuzz/frames.h) that the assembler and
///        ValidateScan accept under FuzzEngineLimits.
/// @details Usage: vasl_fuzz_seeds OUT_DIR RGB_PANORAMA GRAY_PANORAMA JPEG_PANORAMA
///          The panoramas are small 2:1 encoded images (deploy/fuzz.sh makes them with
///          oiiotool). Seeds: XYZI points in 3 chunks, XYZIRGB points, an RGB panorama sent by
///          name in 2 chunks, an IR panorama sent by index, two panoramas with capture time and
///          rig. Points are seeded pseudo-random, so the files are the same every run.
#include <cstdio>
#include <cstring>
#include <fstream>
#include <iostream>
#include <iterator>
#include <random>
#include <string>
#include <vector>

#include "tests/fuzz/frames.h"
#include "vasl/v1/vasl.pb.h"

namespace {

using vasl::v1::IngestScanRequest;

std::string ReadFile(const char* path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    std::cerr << "vasl_fuzz_seeds: cannot read " << path << "\n";
    std::exit(2);
  }
  return std::string(std::istreambuf_iterator<char>(in), {});
}

/// `n` points of `floats` float32 LE values each, in a 10 m box (colour in [0, 1]).
std::string PackPoints(int n, int floats, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> coord(-5.0f, 5.0f), unit(0.0f, 1.0f);
  std::string bytes;
  for (int i = 0; i < n; ++i) {
    for (int k = 0; k < floats; ++k) {
      const float f = k < 3 ? coord(rng) : unit(rng);
      uint32_t bits;
      std::memcpy(&bits, &f, 4);
      for (int b = 0; b < 4; ++b) bytes.push_back(static_cast<char>((bits >> (8 * b)) & 0xff));
    }
  }
  return bytes;
}

struct Pano {
  std::string name;
  vasl::v1::Modality modality;
  std::string image;
};

IngestScanRequest Header(int points, bool colour, const std::vector<Pano>& panos) {
  IngestScanRequest r;
  vasl::v1::ScanHeader* h = r.mutable_header();
  h->set_project("fuzz");
  h->set_scan("scan-1");
  h->mutable_pose()->mutable_position_m()->set_x(1.0);
  h->mutable_pose()->mutable_position_m()->set_z(1.5);
  h->mutable_pose()->mutable_quaternion_xyzw()->set_w(1.0);
  h->mutable_lidar()->set_divergence_rad(3e-4);
  h->mutable_lidar()->set_point_format(colour ? vasl::v1::POINT_FORMAT_XYZIRGB_F32LE
                                              : vasl::v1::POINT_FORMAT_XYZI_F32LE);
  h->mutable_lidar()->set_point_count(points);
  for (const Pano& pano : panos) {
    vasl::v1::PanoramaDescriptor* p = h->add_panoramas();
    p->set_name(pano.name);
    p->set_modality(pano.modality);
    p->mutable_pose()->mutable_position_m()->set_z(1.6);
    p->mutable_pose()->mutable_quaternion_xyzw()->set_z(0.7071067811865476);
    p->mutable_pose()->mutable_quaternion_xyzw()->set_w(0.7071067811865476);
    p->set_encoded_size_bytes(static_cast<int64_t>(pano.image.size()));
  }
  return r;
}

/// Points chunks: `bytes` split at the given point indices.
void AddPoints(const std::string& bytes, int stride, const std::vector<int>& cuts,
               std::vector<std::string>* frames) {
  size_t at = 0;
  std::vector<size_t> ends;
  for (int c : cuts) ends.push_back(size_t(c) * size_t(stride));
  ends.push_back(bytes.size());
  for (size_t end : ends) {
    IngestScanRequest r;
    r.mutable_points()->set_data(bytes.substr(at, end - at));
    frames->push_back(r.SerializeAsString());
    at = end;
  }
}

/// Image chunks of panorama `index` (by name unless `by_index`), in `pieces` chunks.
void AddImage(const Pano& pano, int index, bool by_index, int pieces,
              std::vector<std::string>* frames) {
  const size_t step = (pano.image.size() + size_t(pieces) - 1) / size_t(pieces);
  for (size_t at = 0; at < pano.image.size(); at += step) {
    IngestScanRequest r;
    if (by_index) {
      r.mutable_image()->set_panorama_index(index);
    } else {
      r.mutable_image()->set_panorama_name(pano.name);
    }
    r.mutable_image()->set_data(pano.image.substr(at, step));
    frames->push_back(r.SerializeAsString());
  }
}

void Write(const std::string& dir, const std::string& name, const std::vector<std::string>& frames) {
  const std::string path = dir + "/" + name;
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  const std::string bytes = vasl::fuzz::EncodeFrames(frames);
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  if (!out) {
    std::cerr << "vasl_fuzz_seeds: cannot write " << path << "\n";
    std::exit(1);
  }
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 5) {
    std::cerr << "usage: vasl_fuzz_seeds OUT_DIR RGB_PANORAMA GRAY_PANORAMA JPEG_PANORAMA\n";
    return 2;
  }
  const std::string dir = argv[1];
  const Pano rgb{"cam0", vasl::v1::MODALITY_RGB, ReadFile(argv[2])};
  const Pano ir{"ir0", vasl::v1::MODALITY_IR, ReadFile(argv[3])};
  const Pano jpeg{"cam1", vasl::v1::MODALITY_RGB, ReadFile(argv[4])};
  {
    std::vector<std::string> f{Header(40, false, {}).SerializeAsString()};
    AddPoints(PackPoints(40, 4, 1), 16, {5, 23}, &f);
    Write(dir, "xyzi-3-chunks", f);
  }
  {
    std::vector<std::string> f{Header(12, true, {}).SerializeAsString()};
    AddPoints(PackPoints(12, 7, 2), 28, {7}, &f);
    Write(dir, "xyzirgb-2-chunks", f);
  }
  {
    std::vector<std::string> f{Header(16, false, {rgb}).SerializeAsString()};
    AddPoints(PackPoints(16, 4, 3), 16, {}, &f);
    AddImage(rgb, 0, /*by_index=*/false, 2, &f);
    Write(dir, "rgb-panorama-by-name", f);
  }
  {
    std::vector<std::string> f{Header(8, false, {ir}).SerializeAsString()};
    AddPoints(PackPoints(8, 4, 4), 16, {4}, &f);
    AddImage(ir, 0, /*by_index=*/true, 1, &f);
    Write(dir, "ir-panorama-by-index", f);
  }
  {
    IngestScanRequest header = Header(10, true, {rgb, jpeg});
    header.mutable_header()->set_rig("fuzz-rig");
    header.mutable_header()->mutable_capture_time()->set_seconds(1795000000);
    header.mutable_header()->mutable_panoramas(1)->set_angular_resolution_rad(0.01);
    std::vector<std::string> f{header.SerializeAsString()};
    AddPoints(PackPoints(10, 7, 5), 28, {3, 6}, &f);
    AddImage(rgb, 0, /*by_index=*/true, 1, &f);
    AddImage(jpeg, 1, /*by_index=*/false, 3, &f);
    Write(dir, "two-panoramas-colour-points", f);
  }
  return 0;
}

/// @file fuzz_backproject_image.cc
/// @brief libFuzzer harness over the back-projection's image path (lattice/ingest/backproject.h):
///        ingest::DecodeRgbzImage, the reader of the RGBZ[N,U,A] images that BackProject
///        (vasl backproject) sends, then BackProjectRecords of the decoded image onto a fixed
///        small lattice, as the back-projection flow does. The input is the encoded image,
///        normally an OpenEXR with channels R, G, B, Z and optionally N.x, N.y, N.z, U, A.
/// @details Decodes with kMaxImagePixels (tests/fuzz/fuzz_limits.h). Claims checked: a
///          rejection is INVALID_ARGUMENT or RESOURCE_EXHAUSTED with a message; a decoded image
///          is non-empty and within the pixel limit, has 3 colour and 1 depth value per pixel,
///          and normals (3), uncertainty (1) and coverage (1) per pixel or none. Back-projected
///          from the centre of a 16³ block of vossels (edge 0.25 m), equirect and then pinhole
///          (with distortion, onto every third vossel only): every pixel is counted once as
///          used, outside or empty; records are one per vossel, in vossel order, only on the
///          allowed vossels, with a finite positive range, cosθ in [0, 1] and uv inside the
///          image. Record values are not checked: the image's colours are taken as they are.
///          As with fuzz_image_decode, Debian's OpenImageIO/OpenEXR give libFuzzer no coverage.
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <string_view>
#include <vector>

#include "lattice/ingest/backproject.h"
#include "tests/fuzz/fuzz_check.h"
#include "tests/fuzz/fuzz_limits.h"

namespace {

using vasl::ingest::DerivedImage;
using vasl::ingest::DerivedSource;
using vasl::records::VosselGeometry;

/// 16³ vossels of edge 0.25 m centred on the origin (a 4 m cube); normals alternate between a
/// unit axis and none, so that both cosθ branches run.
const VosselGeometry& Lattice() {
  static const VosselGeometry* geometry = [] {
    auto* g = new VosselGeometry;
    g->vossel_size_m = 0.25;
    g->index_grid = openvdb::Int32Grid::create(-1);
    g->index_grid->setTransform(openvdb::math::Transform::createLinearTransform(g->vossel_size_m));
    openvdb::Int32Grid::Accessor acc = g->index_grid->getAccessor();
    for (int x = -8; x < 8; ++x) {
      for (int y = -8; y < 8; ++y) {
        for (int z = -8; z < 8; ++z) {
          const openvdb::Coord c(x, y, z);
          const int32_t index = static_cast<int32_t>(g->coord.size());
          acc.setValue(c, index);
          g->coord.push_back(c);
          g->point_count.push_back(1);
          g->centroid_m.emplace_back(float(x * g->vossel_size_m), float(y * g->vossel_size_m),
                                     float(z * g->vossel_size_m));
          g->normal.push_back(index % 2 == 0 ? Eigen::Vector3f(0.0f, 0.0f, 1.0f)
                                             : Eigen::Vector3f(0.0f, 0.0f, 0.0f));
          g->covariance_m2.push_back({});
        }
      }
    }
    return g;
  }();
  return *geometry;
}

void CheckDecoded(const DerivedImage& im) {
  VASL_FUZZ_CHECK(im.width_px > 0 && im.height_px > 0 &&
                      int64_t{im.width_px} * im.height_px <= vasl::fuzz::kMaxImagePixels,
                  "decoded a ", im.width_px, "x", im.height_px, " image");
  const size_t n = size_t(im.width_px) * size_t(im.height_px);
  VASL_FUZZ_CHECK(im.rgb.size() == 3 * n, im.rgb.size(), " colour values for ", n, " pixels");
  VASL_FUZZ_CHECK(im.depth_m.size() == n, im.depth_m.size(), " depths for ", n, " pixels");
  VASL_FUZZ_CHECK(im.normal.empty() || im.normal.size() == 3 * n, im.normal.size(),
                  " normal values for ", n, " pixels");
  VASL_FUZZ_CHECK(im.uncertainty.empty() || im.uncertainty.size() == n, im.uncertainty.size(),
                  " uncertainties for ", n, " pixels");
  VASL_FUZZ_CHECK(im.alpha.empty() || im.alpha.size() == n, im.alpha.size(),
                  " coverages for ", n, " pixels");
}

void BackProjectAndCheck(const DerivedSource& source, const std::vector<uint8_t>* only) {
  const VosselGeometry& g = Lattice();
  const DerivedImage& im = source.image;
  vasl::ingest::BackProjectStats stats;
  const vasl::records::RecordSet records = vasl::ingest::BackProjectRecords(g, source, only, &stats);
  const int64_t n = int64_t{im.width_px} * im.height_px;
  VASL_FUZZ_CHECK(stats.pixels_used + stats.pixels_outside + stats.pixels_empty +
                      stats.pixels_invalid == n,
                  "used ", stats.pixels_used, " + outside ", stats.pixels_outside, " + empty ",
                  stats.pixels_empty, " != ", n, " pixels");
  VASL_FUZZ_CHECK(int64_t(records.size()) <= stats.pixels_used && records.size() <= g.size(),
                  records.size(), " records from ", stats.pixels_used, " pixels");
  for (size_t q = 0; q < records.size(); ++q) {
    const int32_t v = records.vossel[q];
    VASL_FUZZ_CHECK(v >= 0 && size_t(v) < g.size() && (q == 0 || records.vossel[q - 1] < v),
                    "record ", q, " is on vossel ", v);
    VASL_FUZZ_CHECK(only == nullptr || (*only)[size_t(v)], "record on excluded vossel ", v);
    VASL_FUZZ_CHECK(std::isfinite(records.range_m[q]) && records.range_m[q] > 0.0f,
                    "record ", q, " has range ", records.range_m[q]);
    VASL_FUZZ_CHECK(records.cos_inc[q] >= 0.0f && records.cos_inc[q] <= 1.0f, "record ", q,
                    " has cos_inc ", records.cos_inc[q]);
    for (int c = 0; c < 3; ++c) {
      VASL_FUZZ_CHECK(std::isfinite(records.value[3 * q + c]), "record ", q, " has value ",
                      records.value[3 * q + c], " in channel ", c);
    }
    const float u = records.uv_px[2 * q], w = records.uv_px[2 * q + 1];
    VASL_FUZZ_CHECK(u >= 0.0f && u <= float(im.width_px) && w >= 0.0f && w <= float(im.height_px),
                    "record ", q, " has uv ", u, ",", w);
  }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string_view bytes(reinterpret_cast<const char*>(data), size);
  absl::StatusOr<DerivedImage> image =
      vasl::ingest::DecodeRgbzImage(bytes, vasl::fuzz::kMaxImagePixels);
  if (!image.ok()) {
    vasl::fuzz::CheckRejection(image.status(), "DecodeRgbzImage");
    return 0;
  }
  CheckDecoded(*image);

  DerivedSource source;
  source.id = 7;
  source.batch = 3;
  source.image = std::move(*image);
  BackProjectAndCheck(source, nullptr);

  source.pinhole = true;
  source.pose.q_world_sensor = Eigen::Quaterniond(Eigen::AngleAxisd(0.3, Eigen::Vector3d::UnitY()));
  source.intrinsics.fx_px = source.intrinsics.fy_px = 0.8 * source.image.width_px;
  source.intrinsics.cx_px = 0.5 * source.image.width_px;
  source.intrinsics.cy_px = 0.5 * source.image.height_px;
  source.intrinsics.k1 = 0.05;
  source.intrinsics.p1 = 0.01;
  std::vector<uint8_t> only(Lattice().size(), 0);
  for (size_t v = 0; v < only.size(); v += 3) only[v] = 1;
  BackProjectAndCheck(source, &only);
  return 0;
}

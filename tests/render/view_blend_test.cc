// VASL-MODEL §8 view term: with η > 0 a render favours the records of scans that saw a vossel
// from near the render's own direction; η = 0 is the fused colour C_k.
#include <algorithm>
#include <cmath>
#include <memory>
#include <optional>
#include <vector>

#include <gtest/gtest.h>

#include "lattice/fusion/fuse.h"
#include "lattice/geometry/equirect.h"
#include "lattice/geometry/pinhole.h"
#include "lattice/records/record_grid.h"
#include "lattice/render/render.h"

namespace vasl::render {
namespace {

constexpr double kVosselM = 0.05;

// A floor patch (z = 0, normal +z) of 40×40 vossels, each seen by two cameras: source 0 low in
// the west (red) and source 1 high overhead (blue), with equal weights.
struct TwoViewFloor {
  records::VosselGeometry geometry;
  records::RecordSet records;
  records::FusedValues fused;
  Eigen::Vector3d west{-3.0, 1.0, 2.0}, top{1.0, 1.0, 6.0};
};

TwoViewFloor MakeFloor() {
  TwoViewFloor f;
  f.geometry.vossel_size_m = kVosselM;
  for (int i = 0; i < 40; ++i)
    for (int j = 0; j < 40; ++j) f.geometry.coord.emplace_back(i, j, 0);
  records::CanonicalizeVosselOrder(f.geometry);
  const size_t n = f.geometry.size();
  f.geometry.point_count.assign(n, 10);
  f.geometry.normal.assign(n, Eigen::Vector3f::UnitZ());
  f.geometry.covariance_m2.assign(n, {});
  for (size_t k = 0; k < n; ++k) {
    const openvdb::Coord c = f.geometry.coord[k];
    f.geometry.centroid_m.emplace_back(float(c.x() * kVosselM), float(c.y() * kVosselM), 0.0f);
  }
  const float red[3] = {0.9f, 0.1f, 0.1f}, blue[3] = {0.1f, 0.1f, 0.9f};
  for (size_t k = 0; k < n; ++k) {
    for (int src = 0; src < 2; ++src) {
      const size_t i = f.records.size();
      f.records.Resize(i + 1);
      f.records.vossel[i] = int32_t(k);
      f.records.scan[i] = src;
      f.records.modality[i] = int8_t(records::Modality::kRgb);
      for (int c = 0; c < 3; ++c) f.records.value[3 * i + c] = (src == 0 ? red : blue)[c];
      f.records.range_m[i] = 4.0f;
      f.records.cos_inc[i] = 1.0f;  // equal weights: the test is about the view term alone
      f.records.foot_major_m[i] = f.records.foot_minor_m[i] = 0.001f;
      f.records.vis[i] = 1.0f;
      for (int c = 0; c < records::kConfidenceCount; ++c) {
        f.records.conf[records::kConfidenceCount * i + c] = 1.0f;
      }
      f.records.flags[i] = 0;
      f.records.batch[i] = 1;
    }
  }
  f.fused = *fusion::Fuse(f.records, n, kVosselM, fusion::WeightingProfile{});
  return f;
}

// Mean rendered colour over hit pixels, and the hit count.
Eigen::Vector3d MeanColour(const RenderImage& image, int64_t* hits) {
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  *hits = 0;
  for (size_t p = 0; p < image.depth_m.size(); ++p) {
    if (!std::isfinite(image.depth_m[p])) continue;
    ++*hits;
    sum += Eigen::Vector3d(image.rgb[3 * p], image.rgb[3 * p + 1], image.rgb[3 * p + 2]);
  }
  return sum / double(std::max<int64_t>(*hits, 1));
}

TEST(ViewBlendTest, ViewTermFavoursScansSeenFromNearTheRenderDirection) {
  const TwoViewFloor f = MakeFloor();
  auto weights = fusion::RecordWeights(f.records, f.geometry.size(), kVosselM, fusion::WeightingProfile{});
  ASSERT_TRUE(weights.ok());
  ViewBlendInputs blend;
  blend.records = &f.records;
  blend.weight = &weights->weight;
  blend.begin = &weights->begin;
  blend.source_origin_m = {f.west, f.top};

  RenderRequest req;
  req.width_px = 512;
  req.height_px = 256;
  req.pose.o_world = Eigen::Vector3d(-2.0, 1.0, 1.5);  // near the west camera
  // η = 0: the fused colour, the even mix of red and blue.
  auto flat = RenderEquirect(f.geometry, f.fused, req, &blend);
  ASSERT_TRUE(flat.ok()) << flat.status();
  int64_t hits = 0;
  const Eigen::Vector3d mix = MeanColour(*flat, &hits);
  ASSERT_GT(hits, 100);
  EXPECT_NEAR(mix.x(), 0.5, 1e-5);
  EXPECT_NEAR(mix.z(), 0.5, 1e-5);
  // η = 8 from the west: the west (red) records dominate; from overhead, the blue ones.
  req.eta = 8.0;
  auto west = RenderEquirect(f.geometry, f.fused, req, &blend);
  ASSERT_TRUE(west.ok()) << west.status();
  const Eigen::Vector3d from_west = MeanColour(*west, &hits);
  req.pose.o_world = Eigen::Vector3d(1.0, 1.0, 5.0);
  auto top = RenderEquirect(f.geometry, f.fused, req, &blend);
  ASSERT_TRUE(top.ok());
  const Eigen::Vector3d from_top = MeanColour(*top, &hits);
  std::printf("η = 8: mean colour seen from the west (%.3f %.3f %.3f), from overhead (%.3f %.3f "
              "%.3f); η = 0: (%.3f %.3f %.3f)\n", from_west.x(), from_west.y(), from_west.z(),
              from_top.x(), from_top.y(), from_top.z(), mix.x(), mix.y(), mix.z());
  EXPECT_GT(from_west.x(), 0.7);
  EXPECT_LT(from_west.z(), 0.3);
  EXPECT_GT(from_top.z(), 0.7);
  EXPECT_LT(from_top.x(), 0.3);
  // Larger η sharpens the preference monotonically.
  req.pose.o_world = Eigen::Vector3d(-2.0, 1.0, 1.5);
  req.eta = 2.0;
  const Eigen::Vector3d mild = MeanColour(*RenderEquirect(f.geometry, f.fused, req, &blend), &hits);
  std::printf("η = 2 from the west: red %.3f (η = 8: %.3f)\n", mild.x(), from_west.x());
  EXPECT_GT(mild.x(), 0.5);
  EXPECT_LT(mild.x(), from_west.x());
}

// The floor's striped albedo for the colour-detail test: bands 7 cm wide along x, so that
// their edges fall anywhere within a 5 cm vossel.
Eigen::Vector3f Stripe(double x) {
  return int(std::floor(x / 0.07)) % 2 == 0 ? Eigen::Vector3f(0.9f, 0.8f, 0.1f)
                                            : Eigen::Vector3f(0.1f, 0.2f, 0.7f);
}

// An image of the striped floor (z = 0) from `pose`: each pixel centre's ray, through the
// projection (equirect, or pinhole when given), coloured where it meets the floor.
geometry::LinearImage FloorImage(const geometry::Pose& pose, int w, int h,
                                 const std::optional<geometry::PinholeIntrinsics>& pinhole) {
  geometry::LinearImage img;
  img.width_px = w;
  img.height_px = h;
  img.channels = 3;
  img.pixels.assign(size_t(w) * h * 3, 0.0f);
  for (int j = 0; j < h; ++j) {
    for (int i = 0; i < w; ++i) {
      const Eigen::Vector3d d_cam =
          pinhole ? geometry::PinholeUnproject(Eigen::Vector2d(i + 0.5, j + 0.5), *pinhole)
                  : geometry::EquirectUnproject(i + 0.5, j + 0.5, {w, h});
      const Eigen::Vector3d d = pose.DirectionToWorld(d_cam);
      if (!(d.z() < 0.0)) continue;
      const Eigen::Vector3d x = pose.o_world - pose.o_world.z() / d.z() * d;
      const Eigen::Vector3f c = Stripe(x.x());
      for (int ch = 0; ch < 3; ++ch) img.pixels[(size_t(j) * w + i) * 3 + ch] = c[ch];
    }
  }
  return img;
}

// Claim (§8, ColourDetail::kSourceImages): with the overhead camera's image (equirect or
// pinhole) each hit pixel's colour is Σ w·S / Σ w over the vossel's records, where the overhead
// record's S is its image read at the pixel's own floor point and the west record, whose source
// has no image, keeps its red C_{k,m}. Away from stripe edges (≥ 2 cm: the image's bilinear read
// is exact there) that equals the analytic blend to 1e-4, so colour changes within a vossel as
// the stripes do, which one colour per vossel cannot.
TEST(ViewBlendTest, ColourDetailReadsTheSourceImagesAtEachPixelsPoint) {
  const TwoViewFloor f = MakeFloor();
  auto weights = fusion::RecordWeights(f.records, f.geometry.size(), kVosselM, fusion::WeightingProfile{});
  ASSERT_TRUE(weights.ok());
  geometry::Pose top;
  top.o_world = f.top;
  geometry::PinholeIntrinsics k;
  k.width_px = k.height_px = 1000;
  k.fx_px = k.fy_px = 1000.0;
  k.cx_px = k.cy_px = 500.0;
  geometry::Pose down = top;  // camera x right (+x), y down (−y), z forward (−z)
  Eigen::Matrix3d R;
  R.col(0) = Eigen::Vector3d::UnitX();
  R.col(1) = -Eigen::Vector3d::UnitY();
  R.col(2) = -Eigen::Vector3d::UnitZ();
  down.q_world_sensor = Eigen::Quaterniond(R);
  for (const bool pinhole : {false, true}) {
    ViewBlendInputs blend;
    blend.records = &f.records;
    blend.weight = &weights->weight;
    blend.begin = &weights->begin;
    blend.source_origin_m = {f.west, f.top};
    blend.images.resize(2);  // source 0 (west): no image
    if (pinhole) {
      blend.images[1] = {down, geometry::ImageProjection(k, 1000, 1000),
                         std::make_shared<geometry::LinearImage>(FloorImage(down, 1000, 1000, k))};
    } else {
      blend.images[1] = {top, geometry::ImageProjection(std::nullopt, 4096, 2048),
                         std::make_shared<geometry::LinearImage>(FloorImage(top, 4096, 2048, {}))};
    }
    RenderRequest req;
    req.width_px = 512;
    req.height_px = 256;
    req.pose.o_world = Eigen::Vector3d(1.0, 1.0, 2.0);
    req.colour_detail = ColourDetail::kSourceImages;
    // Streamed rows (§8 outputs) are final only once their colour detail is applied: the
    // march hands on none, ApplyColourDetail hands on every row, each with its final colour.
    bool detailed = false;
    int handed = 0;
    std::vector<float> handed_rgb(3 * size_t(req.width_px) * req.height_px, -1.0f);
    req.rows_done = [&](const RenderImage& im, int row_begin, int row_end) {
      EXPECT_TRUE(detailed) << "rows handed on before their colour detail";
      EXPECT_EQ(row_begin, handed);
      handed = row_end;
      const size_t a = 3 * size_t(row_begin) * im.width_px, b = 3 * size_t(row_end) * im.width_px;
      std::copy(im.rgb.begin() + a, im.rgb.begin() + b, handed_rgb.begin() + a);
      return absl::OkStatus();
    };
    auto image = RenderEquirect(f.geometry, f.fused, req, &blend);
    ASSERT_TRUE(image.ok()) << image.status();
    detailed = true;
    ASSERT_TRUE(ApplyColourDetail(f.geometry, req, blend, &*image).ok());
    EXPECT_EQ(handed, req.height_px);
    EXPECT_TRUE(handed_rgb == image->rgb);
    EXPECT_EQ(image->detail_sources, 1);
    int64_t checked = 0, mismatched = 0, varying_vossels = 0;
    double max_err = 0.0;
    std::vector<float> first_seen(3 * f.geometry.size(), -1.0f);
    std::vector<uint8_t> varies(f.geometry.size(), 0);
    for (int j = 0; j < req.height_px; ++j) {
      for (int i = 0; i < req.width_px; ++i) {
        const size_t p = size_t(j) * req.width_px + i;
        const int32_t v = image->vossel_index[p];
        if (v < 0) continue;
        const Eigen::Vector3d d = req.pose.DirectionToWorld(
            geometry::EquirectUnproject(i + 0.5, j + 0.5, {req.width_px, req.height_px}));
        const Eigen::Vector3d x = req.pose.o_world + double(image->depth_m[p]) * d;
        if (float* seen = &first_seen[3 * size_t(v)]; seen[0] < 0.0f) {
          std::copy_n(&image->rgb[3 * p], 3, seen);
        } else if (std::abs(seen[0] - image->rgb[3 * p]) > 0.3f) {
          varies[size_t(v)] = 1;
        }
        const double u = x.x() / 0.07;
        if (std::abs(u - std::round(u)) * 0.07 < 0.02) continue;  // near a stripe edge
        const size_t b = weights->begin[size_t(v)];
        ASSERT_EQ(weights->begin[size_t(v) + 1], b + 2);
        const double w0 = weights->weight[b], w1 = weights->weight[b + 1];  // west, top
        const Eigen::Vector3f stripe = Stripe(x.x());
        const double red[3] = {0.9, 0.1, 0.1};
        for (int c = 0; c < 3; ++c) {
          const double expect = (w0 * red[c] + w1 * stripe[c]) / (w0 + w1);
          const double err = std::abs(image->rgb[3 * p + c] - expect);
          max_err = std::max(max_err, err);
          mismatched += err > 1e-4;
        }
        ++checked;
      }
    }
    varying_vossels = std::count(varies.begin(), varies.end(), uint8_t{1});
    std::printf("colour detail from a%s image: %lld pixels checked, max error %.2g, %lld of %zu "
                "vossels show two stripes\n", pinhole ? " pinhole" : "n equirect",
                (long long)checked, max_err, (long long)varying_vossels, f.geometry.size());
    EXPECT_GT(checked, 5000);
    EXPECT_EQ(mismatched, 0);
    EXPECT_GT(varying_vossels, 100);
  }
  // Without the vossel indices of a kSourceImages render there is nothing to recolour.
  RenderRequest plain;
  plain.width_px = 64;
  plain.height_px = 32;
  auto image = RenderEquirect(f.geometry, f.fused, plain);
  ASSERT_TRUE(image.ok());
  ViewBlendInputs blend;
  blend.records = &f.records;
  blend.weight = &weights->weight;
  blend.begin = &weights->begin;
  EXPECT_EQ(ApplyColourDetail(f.geometry, plain, blend, &*image).code(),
            absl::StatusCode::kInvalidArgument);
}

TEST(ViewBlendTest, EtaNeedsTheRecords) {
  const TwoViewFloor f = MakeFloor();
  RenderRequest req;
  req.width_px = 64;
  req.height_px = 32;
  req.eta = 1.0;
  EXPECT_EQ(RenderEquirect(f.geometry, f.fused, req).status().code(),
            absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace vasl::render

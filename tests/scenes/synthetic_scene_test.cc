// Claims of the synthetic scene generator (tests/scenes/synthetic_scene.h): the scene meets its
// specification, LiDAR points lie on the analytic surfaces within the stated noise, the shadow
// region is shadowed/lit as documented, panoramas integrate over the pixel footprint (§2.1),
// seams wrap, and the PNG / PLY / .npy writers produce what readers expect.
#include "tests/scenes/synthetic_scene.h"

#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>

#include <algorithm>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <random>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "lattice/geometry/equirect.h"

namespace vasl::scenes {
namespace {

using Eigen::Vector3d;
namespace fs = std::filesystem;

fs::path TempPath(const std::string& name) {
  const fs::path dir = fs::temp_directory_path() / "vasl_synthetic_scene_test";
  fs::create_directories(dir);
  return dir / name;
}

std::string ReadAll(const fs::path& p) {
  std::ifstream f(p, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(f), std::istreambuf_iterator<char>());
}

bool InsideBox(const Vector3d& p, const Aabb& b, double shrink_m) {
  for (int a = 0; a < 3; ++a) {
    if (p[a] < b.min_m[a] + shrink_m || p[a] > b.max_m[a] - shrink_m) return false;
  }
  return true;
}

double DistanceToBox(const Vector3d& p, const Aabb& b) {
  Vector3d d;
  for (int a = 0; a < 3; ++a) d[a] = std::max({b.min_m[a] - p[a], 0.0, p[a] - b.max_m[a]});
  return d.norm();
}

double Percentile(std::vector<double> v, double q) {
  if (v.empty()) return 0.0;
  const size_t k = std::min(v.size() - 1, static_cast<size_t>(q * (v.size() - 1)));
  std::nth_element(v.begin(), v.begin() + k, v.end());
  return v[k];
}

// Claim: the canonical scene is the specified one: ≥ 3 stations 1.2–1.6 m above the floor,
// ≥ 1 m from walls and box, at least one yawed; novel views inside, not at a station; albedo in
// [0.05, 0.95] and smooth (change per 0.05 m vossel: worst ≤ 0.08, RMS ≤ 0.025, so a renderer
// that is right to within a vossel keeps PSNR well above 30 dB); the box differs from the wall
// behind it.
TEST(SyntheticSceneTest, CanonicalSceneMeetsItsSpecification) {
  const SyntheticRoom room = SyntheticRoom::Default();
  const Aabb& r = room.RoomBounds();
  const Aabb& box = room.OccluderBounds();
  const auto stations = room.Stations();
  ASSERT_GE(stations.size(), 3u);
  int yawed = 0;
  for (const auto& s : stations) {
    const Vector3d o = s.o_world;
    EXPECT_GE(o.z(), 1.2);
    EXPECT_LE(o.z(), 1.6);
    const double wall = std::min({o.x() - r.min_m.x(), r.max_m.x() - o.x(), o.y() - r.min_m.y(),
                                  r.max_m.y() - o.y()});
    EXPECT_GE(wall, 1.0);
    EXPECT_GE(DistanceToBox(o, box), 1.0);
    if (s.q_world_sensor.angularDistance(Eigen::Quaterniond::Identity()) > 0.1) ++yawed;
    std::printf("station (%.2f, %.2f, %.2f): %.2f m from walls, %.2f m from box\n", o.x(), o.y(),
                o.z(), wall, DistanceToBox(o, box));
  }
  EXPECT_GE(yawed, 1);
  ASSERT_GE(room.NovelViews().size(), 1u);
  for (const auto& v : room.NovelViews()) {
    EXPECT_TRUE(InsideBox(v.o_world, r, 0.3));
    EXPECT_GT(DistanceToBox(v.o_world, box), 0.3);
    for (const auto& s : stations) {
      EXPECT_GT((v.o_world - s.o_world).norm(), 0.5);
      EXPECT_GT((v.o_world - CameraPoseForStation(s).o_world).norm(), 0.5);
    }
  }
  // Albedo range and smoothness on every face, sampled densely.
  std::mt19937_64 rng(3);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  float lo = 1.0f, hi = 0.0f;
  double worst_step = 0.0, sum_step2 = 0.0;
  int steps = 0;
  for (int face = 0; face < kFaceCount; ++face) {
    for (int k = 0; k < 20000; ++k) {
      const Vector3d x(u(rng) * 6.0, u(rng) * 5.0, u(rng) * 3.0);
      const Eigen::Vector3f a = room.Albedo(x, face);
      lo = std::min(lo, a.minCoeff());
      hi = std::max(hi, a.maxCoeff());
      Vector3d step = Vector3d(u(rng) - 0.5, u(rng) - 0.5, u(rng) - 0.5);
      step = 0.05 * step.normalized();
      const double change = (room.Albedo(x + step, face) - a).cwiseAbs().maxCoeff();
      worst_step = std::max(worst_step, change);
      sum_step2 += change * change;
      ++steps;
    }
  }
  // Mean colour of the box's y-min face versus the wall behind it (y = max).
  Eigen::Vector3d box_mean = Eigen::Vector3d::Zero(), wall_mean = Eigen::Vector3d::Zero();
  const int n = 2000;
  for (int k = 0; k < n; ++k) {
    box_mean += room.Albedo({2.6 + 0.8 * u(rng), 2.3, 1.8 * u(rng)}, kFaceBoxYMin).cast<double>();
    wall_mean += room.Albedo({1.6 + 2.8 * u(rng), 5.0, 2.8 * u(rng)}, kFaceWallYMax).cast<double>();
  }
  const double contrast = (box_mean - wall_mean).norm() / n;
  const double rms_step = std::sqrt(sum_step2 / steps);
  std::printf("albedo range [%.3f, %.3f]; change over a 0.05 m step: worst %.4f, RMS %.4f; "
              "box-vs-wall mean colour distance %.3f\n",
              lo, hi, worst_step, rms_step, contrast);
  EXPECT_GE(lo, 0.05f);
  EXPECT_LE(hi, 0.95f);
  EXPECT_LE(worst_step, 0.08);
  EXPECT_LE(rms_step, 0.025);
  EXPECT_GE(contrast, 0.3);
}

// Claim: every LiDAR point lies on the analytic surface along its own ray, within the range
// noise: ≥ 99.9% within 4σ, the residual mean within 0.1σ and its σ within 5% of the setting.
// Points are in the sensor frame (the yawed pose matters), intensity is the luminance of the
// albedo at the hit, the nadir cone of 10° is empty and the generator is deterministic.
TEST(SyntheticSceneTest, LidarPointsLieOnAnalyticSurfaces) {
  const SyntheticRoom room = SyntheticRoom::Default();
  LidarSettings settings;
  settings.azimuth_steps = 720;
  settings.elevation_steps = 360;
  settings.seed = 11;
  const double sigma = settings.range_noise_m;
  for (int station : {0, 1}) {
    const geometry::Pose pose = room.Stations()[station];
    const LidarScan scan = GenerateLidar(room, pose, settings);
    const size_t n = scan.intensity.size();
    ASSERT_EQ(scan.xyz_sensor_m.size(), 3 * n);
    // A closed room: every ray outside the nadir cone returns (rows whose centre is above −80°).
    int kept_rows = 0;
    for (int j = 0; j < settings.elevation_steps; ++j) kept_rows += LidarRowKept(settings, j);
    EXPECT_EQ(n, static_cast<size_t>(kept_rows) * settings.azimuth_steps);
    size_t within = 0, wrong_intensity = 0, outside_room_if_world = 0;
    double sum = 0.0, sum2 = 0.0, lowest_elev = M_PI;
    for (size_t k = 0; k < n; ++k) {
      const Vector3d p(scan.xyz_sensor_m[3 * k], scan.xyz_sensor_m[3 * k + 1],
                       scan.xyz_sensor_m[3 * k + 2]);
      const double range = p.norm();
      const Vector3d d_world = pose.DirectionToWorld(p / range);
      const SceneHit hit = room.Intersect(pose.o_world, d_world, 1e9);
      ASSERT_TRUE(hit.valid);
      const double res = range - hit.t_m;
      sum += res;
      sum2 += res * res;
      if (std::abs(res) <= 4.0 * sigma) ++within;
      if (std::abs(scan.intensity[k] - Luminance(room.Albedo(hit.x_world, hit.face))) > 1e-6) {
        ++wrong_intensity;
      }
      if (!InsideBox(pose.o_world + p, room.RoomBounds(), -0.05)) ++outside_room_if_world;
      lowest_elev = std::min(lowest_elev, std::asin(p.z() / range));
    }
    const double mean = sum / n, sd = std::sqrt(sum2 / n - mean * mean);
    const double frac = static_cast<double>(within) / n;
    std::printf("station %d: %zu points; %.4f%% within 4σ; residual mean %.2e m, σ %.3e m "
                "(setting %.1e); lowest elevation %.2f°; %zu points would leave the room "
                "without the pose rotation\n",
                station, n, 100.0 * frac, mean, sd, sigma, lowest_elev * 180 / M_PI,
                outside_room_if_world);
    EXPECT_GE(frac, 0.999);
    EXPECT_LT(std::abs(mean), 0.1 * sigma);
    EXPECT_NEAR(sd, sigma, 0.05 * sigma);
    EXPECT_EQ(wrong_intensity, 0u);
    EXPECT_GE(lowest_elev, -M_PI / 2 + settings.nadir_blind_rad - 1e-6);
    EXPECT_GT(outside_room_if_world, n / 20);  // the sensor frame is not the world frame
  }
  // Deterministic for a seed, different across seeds.
  const LidarScan a = GenerateLidar(room, room.Stations()[2], settings);
  const LidarScan b = GenerateLidar(room, room.Stations()[2], settings);
  settings.seed = 12;
  const LidarScan c = GenerateLidar(room, room.Stations()[2], settings);
  EXPECT_EQ(a.xyz_sensor_m, b.xyz_sensor_m);
  EXPECT_NE(a.xyz_sensor_m, c.xyz_sensor_m);
}

// Claim: the shadow samples on wall y = max are hidden by the occluder from station 0 (the
// segment crosses the box's interior, checked by marching the segment at 1 mm) and reach
// station 1 unobstructed; the lit samples reach both. Range along the LiDAR rays agrees.
TEST(SyntheticSceneTest, ShadowRegionIsShadowedFromStation0AndLitFromStation1) {
  const SyntheticRoom room = SyntheticRoom::Default();
  const auto stations = room.Stations();
  const std::vector<Vector3d> shadow = room.ShadowSamples();
  const std::vector<Vector3d> lit = room.LitSamples();
  ASSERT_GE(shadow.size(), 50u);
  ASSERT_GE(lit.size(), 50u);
  const Aabb& box = room.OccluderBounds();
  auto crosses_box = [&](const Vector3d& o, const Vector3d& x) {
    const double len = (x - o).norm();
    const int steps = static_cast<int>(len / 0.001);
    for (int k = 1; k < steps; ++k) {
      if (InsideBox(o + (x - o) * (static_cast<double>(k) / steps), box, 0.0)) return true;
    }
    return false;
  };
  double zmin = 1e9, zmax = -1e9, xmin = 1e9, xmax = -1e9;
  for (const Vector3d& p : shadow) {
    EXPECT_NEAR(p.y(), room.RoomBounds().max_m.y(), 1e-12);
    for (const Vector3d& o : {stations[0].o_world, CameraPoseForStation(stations[0]).o_world}) {
      EXPECT_FALSE(room.Visible(o, p));
      EXPECT_TRUE(crosses_box(o, p));
      const SceneHit hit = room.Intersect(o, (p - o).normalized(), 1e9);
      EXPECT_GE(hit.face, kFaceBoxXMin);
      EXPECT_LT(hit.t_m, (p - o).norm() - 0.5);
    }
    for (const Vector3d& o : {stations[1].o_world, CameraPoseForStation(stations[1]).o_world}) {
      EXPECT_TRUE(room.Visible(o, p));
      EXPECT_FALSE(crosses_box(o, p));
    }
    zmin = std::min(zmin, p.z()), zmax = std::max(zmax, p.z());
    xmin = std::min(xmin, p.x()), xmax = std::max(xmax, p.x());
  }
  for (const Vector3d& p : lit) {
    for (int s : {0, 1}) {
      EXPECT_TRUE(room.Visible(stations[s].o_world, p));
      EXPECT_FALSE(crosses_box(stations[s].o_world, p));
      const SceneHit hit = room.Intersect(stations[s].o_world,
                                          (p - stations[s].o_world).normalized(), 1e9);
      EXPECT_EQ(hit.face, kFaceWallYMax);
      EXPECT_NEAR(hit.t_m, (p - stations[s].o_world).norm(), 1e-9);
    }
  }
  std::printf("shadow samples: %zu (%.2f m² at 0.1 m pitch), x ∈ [%.2f, %.2f], "
              "z ∈ [%.2f, %.2f]; lit samples: %zu\n",
              shadow.size(), shadow.size() * 0.01, xmin, xmax, zmin, zmax, lit.size());
}

// Claim (§2.1 pixel footprint): a panorama pixel is the mean over its area. Where every
// sub-ray hits one smooth face, integration equals centre-point sampling (the texture is flat
// at pixel scale: 99.9th percentile |Δ| < 0.005); on the occluder's silhouette it does not
// (median |Δ| > 0.02), and there it equals a slow reference mean over the sub-rays (1e-6).
// Depth is the centre ray's range: for pixels on the floor, depth·sin(−ψ) = camera height.
TEST(SyntheticSceneTest, PanoramaIntegratesOverPixelFootprint) {
  const SyntheticRoom room = SyntheticRoom::Default();
  const geometry::Pose cam = CameraPoseForStation(room.Stations()[0]);
  const int w = 512, h = 256, s = 4;
  const Panorama integrated = RenderPanorama(room, cam, w, h, s);
  const Panorama point = RenderPanorama(room, cam, w, h, 1);
  ASSERT_EQ(integrated.rgb.size(), static_cast<size_t>(w * h * 3));
  ASSERT_EQ(integrated.depth_m.size(), static_cast<size_t>(w * h));
  const geometry::EquirectSize size{w, h};
  std::vector<double> flat_diff, edge_diff;
  double worst_reference = 0.0, worst_floor = 0.0;
  int floor_pixels = 0;
  for (int j = 0; j < h; ++j) {
    for (int i = 0; i < w; ++i) {
      bool box = false, other = false;
      int first_face = kFaceNone;
      bool single = true;
      Eigen::Vector3d mean = Eigen::Vector3d::Zero();
      for (int b = 0; b < s; ++b) {
        for (int a = 0; a < s; ++a) {
          const Vector3d d = cam.DirectionToWorld(
              geometry::EquirectUnproject(i + (a + 0.5) / s, j + (b + 0.5) / s, size));
          const SceneHit hit = room.Intersect(cam.o_world, d, 1e9);
          if (first_face == kFaceNone) first_face = hit.face;
          single = single && hit.face == first_face;
          (hit.face >= kFaceBoxXMin ? box : other) = true;
          mean += room.Albedo(hit.x_world, hit.face).cast<double>() / (s * s);
        }
      }
      const size_t p = static_cast<size_t>(j) * w + i;
      double diff = 0.0;
      for (int c = 0; c < 3; ++c) {
        diff = std::max(diff, static_cast<double>(std::abs(integrated.rgb[3 * p + c] -
                                                           point.rgb[3 * p + c])));
        worst_reference = std::max(worst_reference, std::abs(integrated.rgb[3 * p + c] - mean[c]));
      }
      if (single) flat_diff.push_back(diff);
      if (box && other) edge_diff.push_back(diff);
      // Depth semantics on the floor (centre ray).
      const Vector3d d_centre =
          cam.DirectionToWorld(geometry::EquirectUnproject(i + 0.5, j + 0.5, size));
      const SceneHit centre = room.Intersect(cam.o_world, d_centre, 1e9);
      if (centre.face == kFaceFloor) {
        ++floor_pixels;
        worst_floor = std::max(worst_floor, std::abs(integrated.depth_m[p] * -d_centre.z() -
                                                     cam.o_world.z()));
      }
    }
  }
  const double flat_999 = Percentile(flat_diff, 0.999), flat_med = Percentile(flat_diff, 0.5);
  const double edge_med = Percentile(edge_diff, 0.5);
  std::printf("single-face pixels: %zu, |integrated − point| median %.2e, 99.9th pct %.2e; "
              "silhouette pixels: %zu, median %.3f; worst vs slow reference %.2e; floor depth "
              "check over %d pixels: worst %.2e m\n",
              flat_diff.size(), flat_med, flat_999, edge_diff.size(), edge_med, worst_reference,
              floor_pixels, worst_floor);
  ASSERT_GT(flat_diff.size(), static_cast<size_t>(w * h / 2));
  ASSERT_GE(edge_diff.size(), 50u);
  EXPECT_LT(flat_999, 0.005);
  EXPECT_GT(edge_med, 0.02);
  EXPECT_LT(worst_reference, 1e-5);
  EXPECT_GT(floor_pixels, w * h / 10);
  EXPECT_LT(worst_floor, 1e-4);
}

// Claim (§2.1 seam): columns wrap. Rotating the camera by a yaw of π shifts the panorama by
// exactly W/2 columns, so the seam columns of one are the centre columns of the other and must
// agree; and across the seam, neighbouring columns 0 and W−1 differ no more than columns W/2−1
// and W/2 do.
TEST(SyntheticSceneTest, SeamColumnsWrap) {
  const SyntheticRoom room = SyntheticRoom::Default();
  const geometry::Pose cam = CameraPoseForStation(room.Stations()[1]);  // box across its seam
  geometry::Pose turned = cam;
  turned.q_world_sensor = Eigen::Quaterniond(Eigen::AngleAxisd(M_PI, Vector3d::UnitZ())) *
                          cam.q_world_sensor;
  const int w = 512, h = 256;
  const Panorama a = RenderPanorama(room, cam, w, h, 4);
  const Panorama b = RenderPanorama(room, turned, w, h, 4);
  std::vector<double> shift_diff;
  double seam_step = 0.0, centre_step = 0.0, seam_shift_worst = 0.0;
  for (int j = 0; j < h; ++j) {
    for (int i = 0; i < w; ++i) {
      const size_t pa = static_cast<size_t>(j) * w + geometry::WrapColumn(i + w / 2, w);
      const size_t pb = static_cast<size_t>(j) * w + i;
      double diff = 0.0;
      for (int c = 0; c < 3; ++c) {
        diff = std::max(diff, static_cast<double>(std::abs(a.rgb[3 * pa + c] - b.rgb[3 * pb + c])));
      }
      shift_diff.push_back(diff);
      if (i == 0 || i == w - 1 || i == w / 2 - 1 || i == w / 2) {
        seam_shift_worst = std::max(seam_shift_worst, diff);
      }
    }
    for (int c = 0; c < 3; ++c) {
      seam_step += std::abs(a.rgb[3 * (j * w + 0) + c] - a.rgb[3 * (j * w + w - 1) + c]);
      centre_step += std::abs(a.rgb[3 * (j * w + w / 2) + c] - a.rgb[3 * (j * w + w / 2 - 1) + c]);
    }
  }
  seam_step /= 3 * h;
  centre_step /= 3 * h;
  const double p999 = Percentile(shift_diff, 0.999);
  std::printf("yaw-π shift by W/2: 99.9th pct |Δ| %.2e, worst on seam/centre columns %.2e; "
              "mean step across seam %.4f vs across centre %.4f\n",
              p999, seam_shift_worst, seam_step, centre_step);
  EXPECT_LT(p999, 1e-4);
  EXPECT_LT(seam_shift_worst, 0.1);  // at most one sub-ray of 16 flips face at an edge
  EXPECT_LT(seam_step, 3.0 * centre_step + 0.01);
}

// Claim: the PNG decodes (OpenImageIO, from memory) to exactly the 8-bit sRGB values ToSrgb8
// computes, with the sRGB transfer (linear 0.5 → 188, 0.05 → 63).
TEST(SyntheticSceneTest, PngRoundTripDecodesToSame8BitValues) {
  const SyntheticRoom room = SyntheticRoom::Default();
  const Panorama pano = RenderPanorama(room, room.NovelViews()[0], 256, 128, 2);
  absl::StatusOr<std::string> png = EncodePng(pano);
  ASSERT_TRUE(png.ok()) << png.status();
  ASSERT_GT(png->size(), 8u);
  EXPECT_EQ(png->substr(1, 3), "PNG");
  OIIO::Filesystem::IOMemReader reader(png->data(), png->size());
  auto in = OIIO::ImageInput::open("decode.png", nullptr, &reader);
  ASSERT_TRUE(in) << OIIO::geterror();
  const OIIO::ImageSpec& spec = in->spec();
  EXPECT_EQ(spec.width, 256);
  EXPECT_EQ(spec.height, 128);
  EXPECT_EQ(spec.nchannels, 3);
  EXPECT_EQ(spec.format, OIIO::TypeDesc::UINT8);
  std::vector<uint8_t> decoded(256 * 128 * 3);
  ASSERT_TRUE(in->read_image(0, 0, 0, 3, OIIO::TypeDesc::UINT8, decoded.data()));
  in->close();
  const std::vector<uint8_t> expected = ToSrgb8(pano);
  size_t mismatches = 0;
  for (size_t k = 0; k < expected.size(); ++k) mismatches += decoded[k] != expected[k];
  std::printf("PNG: %zu bytes for 256x128, %zu of %zu bytes differ after decode\n", png->size(),
              mismatches, expected.size());
  EXPECT_EQ(mismatches, 0u);
  Panorama probe;
  probe.width_px = 2;
  probe.height_px = 1;
  probe.rgb = {0.5f, 0.05f, 0.0f, 1.0f, 0.0031308f, 0.2f};
  const std::vector<uint8_t> srgb = ToSrgb8(probe);
  EXPECT_EQ(srgb[0], 188);
  EXPECT_EQ(srgb[1], 63);
  EXPECT_EQ(srgb[2], 0);
  EXPECT_EQ(srgb[3], 255);
  Panorama bad;
  bad.width_px = 4;
  bad.height_px = 2;
  EXPECT_EQ(EncodePng(bad).status().code(), absl::StatusCode::kInvalidArgument);
}

// Claim: the PLY has the documented header (binary_little_endian, vertex count, float x y z
// intensity) followed by exactly 16 bytes per point holding the scan's values.
TEST(SyntheticSceneTest, PlyHasHeaderAndCount) {
  const SyntheticRoom room = SyntheticRoom::Default();
  LidarSettings settings;
  settings.azimuth_steps = 90;
  settings.elevation_steps = 45;
  const LidarScan scan = GenerateLidar(room, room.Stations()[0], settings);
  const size_t n = scan.intensity.size();
  const fs::path path = TempPath("scan.ply");
  ASSERT_TRUE(WritePly(scan, path).ok());
  const std::string bytes = ReadAll(path);
  const std::string header = "ply\nformat binary_little_endian 1.0\nelement vertex " +
                             std::to_string(n) +
                             "\nproperty float x\nproperty float y\nproperty float z\n"
                             "property float intensity\nend_header\n";
  ASSERT_EQ(bytes.substr(0, header.size()), header);
  EXPECT_EQ(bytes.size(), header.size() + 16 * n);
  float first[4], last[4];
  std::memcpy(first, bytes.data() + header.size(), 16);
  std::memcpy(last, bytes.data() + bytes.size() - 16, 16);
  EXPECT_EQ(first[0], scan.xyz_sensor_m[0]);
  EXPECT_EQ(first[2], scan.xyz_sensor_m[2]);
  EXPECT_EQ(first[3], scan.intensity[0]);
  EXPECT_EQ(last[1], scan.xyz_sensor_m[3 * n - 2]);
  EXPECT_EQ(last[3], scan.intensity[n - 1]);
  std::printf("PLY: %zu points, header %zu bytes, file %zu bytes\n", n, header.size(),
              bytes.size());
  LidarScan bad = scan;
  bad.intensity.pop_back();
  EXPECT_EQ(WritePly(bad, TempPath("bad.ply")).code(), absl::StatusCode::kInvalidArgument);
}

// Claim: .npy files follow numpy format v1.0: magic, version 1.0, little-endian header length,
// a dict with '<f4', C order and the shape, padded so data starts on a 64-byte boundary.
TEST(SyntheticSceneTest, NpyHeaderBytes) {
  std::vector<float> data(2 * 3 * 3);
  for (size_t k = 0; k < data.size(); ++k) data[k] = 0.5f * k;
  data[4] = std::numeric_limits<float>::infinity();
  const fs::path path = TempPath("a.npy");
  ASSERT_TRUE(WriteNpy(data, {2, 3, 3}, path).ok());
  const std::string bytes = ReadAll(path);
  ASSERT_GT(bytes.size(), 10u);
  EXPECT_EQ(bytes.substr(0, 6), std::string("\x93NUMPY"));
  EXPECT_EQ(bytes[6], 1);
  EXPECT_EQ(bytes[7], 0);
  const size_t header_len =
      static_cast<uint8_t>(bytes[8]) | (static_cast<size_t>(static_cast<uint8_t>(bytes[9])) << 8);
  const std::string header = bytes.substr(10, header_len);
  EXPECT_EQ((10 + header_len) % 64, 0u);
  EXPECT_EQ(header.back(), '\n');
  EXPECT_EQ(header.rfind("{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3, 3), }", 0), 0u)
      << header;
  ASSERT_EQ(bytes.size(), 10 + header_len + 4 * data.size());
  std::vector<float> back(data.size());
  std::memcpy(back.data(), bytes.data() + 10 + header_len, 4 * data.size());
  EXPECT_EQ(back, data);
  std::printf("npy: header %zu bytes: %s", header_len, header.c_str());
  ASSERT_TRUE(WriteNpy({1.0f, 2.0f}, {2}, TempPath("b.npy")).ok());
  EXPECT_NE(ReadAll(TempPath("b.npy")).find("'shape': (2,), }"), std::string::npos);
  EXPECT_EQ(WriteNpy(data, {4, 4}, TempPath("c.npy")).code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace vasl::scenes

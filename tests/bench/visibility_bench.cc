// The §5 kernels an ingest and its revisits spend most of their time in, under Google
// Benchmark (deploy/bench.sh): a source's depth panorama splatted from every vossel of the
// lattice, its dilation, and the visibility test of every vossel, on the corridor site
// (tests/scenes/corridor_site.h) voxelised from all 12 stations as the growth benchmark's last
// scan sees it (LiDAR 1440×720 per station, h = 5 cm), from the last station and from the
// second (items are vossels); the §8 render's march over that lattice and over the same
// scans at h = 2 cm (items are rays), and the encoding of that render into EXR and PNG
// (items are pixels).
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <mutex>

#include <benchmark/benchmark.h>

#include "lattice/geometry/equirect.h"
#include "lattice/ingest/visibility.h"
#include "lattice/ingest/voxelise.h"
#include "lattice/render/encode.h"
#include "lattice/render/render.h"
#include "tests/scenes/corridor_site.h"

namespace {

using vasl::ingest::DepthPanorama;

constexpr double kVosselM = 0.05;
/// A camera's depth panorama as the growth benchmark's 2048×1024 panoramas give it, and the
/// LiDAR's (1440×720 returns: LidarDepthPitchRad).
constexpr double kCameraPitchRad = 2.0 * M_PI / 2048;
constexpr double kLidarPitchRad = M_PI / 720;
constexpr double kCameraDivergenceRad = 2.0 * M_PI / 2048;
constexpr double kLidarDivergenceRad = 0.3e-3;

const vasl::scenes::CorridorSite& Site() {
  static const vasl::scenes::CorridorSite site = vasl::scenes::CorridorSite::Default();
  return site;
}

/// The corridor voxelised from all 12 stations at vossel edge h (5 cm: the growth benchmark's;
/// 2 cm: the realistic site's), built once per h.
const vasl::records::VosselGeometry& Geometry(double h = kVosselM) {
  static std::map<double, vasl::records::VosselGeometry> built_by_h;
  static std::mutex mu;
  std::lock_guard<std::mutex> lock(mu);
  if (auto it = built_by_h.find(h); it != built_by_h.end()) return it->second;
  vasl::scenes::LidarSettings settings;
  settings.azimuth_steps = 1440;
  settings.elevation_steps = 720;
  auto built = vasl::ingest::BuildGeometry(vasl::scenes::StationLidars(Site(), settings), h);
  if (!built.ok()) {
    std::fprintf(stderr, "corridor geometry: %s\n", built.status().ToString().c_str());
    std::exit(1);
  }
  return built_by_h.emplace(h, std::move(*built)).first->second;
}

DepthPanorama Render(size_t station, double pitch_rad, double divergence_rad) {
  return vasl::ingest::RenderDepthPanorama(Geometry(), Site().Stations()[station],
                                           vasl::ingest::DepthPanoramaSize(pitch_rad),
                                           divergence_rad);
}

/// The depth panorama of every vossel from `station`.
void BM_DepthPanorama(benchmark::State& state, size_t station, double pitch_rad,
                      double divergence_rad) {
  Geometry();  // built once, outside the timing
  for (auto _ : state) {
    DepthPanorama d = Render(station, pitch_rad, divergence_rad);
    benchmark::DoNotOptimize(d.depth_m.data());
  }
  state.SetItemsProcessed(int64_t(state.iterations()) * int64_t(Geometry().size()));
  state.counters["vossels"] = double(Geometry().size());
}

/// A camera's dilation (2 pixels) of that panorama.
void BM_Dilate(benchmark::State& state, size_t station) {
  const DepthPanorama d = Render(station, kCameraPitchRad, kCameraDivergenceRad);
  for (auto _ : state) {
    state.PauseTiming();
    DepthPanorama copy = d;
    state.ResumeTiming();
    vasl::ingest::DilateDepthPanorama(copy, 2);
    benchmark::DoNotOptimize(copy.depth_m.data());
  }
  state.SetItemsProcessed(int64_t(state.iterations()) * int64_t(d.depth_m.size()));
}

/// The visibility test of every vossel on that panorama (a LiDAR's: one slope pixel).
void BM_Visibility(benchmark::State& state, size_t station, double pitch_rad,
                   double divergence_rad, int slope_pixels) {
  const DepthPanorama d = Render(station, pitch_rad, divergence_rad);
  const double tau = vasl::ingest::DepthToleranceM(kVosselM);
  size_t shadow = 0;
  for (auto _ : state) {
    const std::vector<float> v =
        vasl::ingest::ComputeVisibility(Geometry(), d, tau, nullptr, slope_pixels);
    shadow = size_t(std::count(v.begin(), v.end(), 0.0f));
    benchmark::DoNotOptimize(v.data());
  }
  state.SetItemsProcessed(int64_t(state.iterations()) * int64_t(Geometry().size()));
  state.counters["shadow"] = double(shadow);
}

/// The §8 render's march alone (RenderEquirect, no colour fused): a W×W/2 equirect image from
/// the corridor's first novel view. Items are rays. `image_fnv` (32-bit FNV-1a of the depth
/// and normal arrays' bytes) tells whether a change to the march kept the image bit for bit.
void BM_Render(benchmark::State& state, double h, int width_px) {
  const vasl::records::VosselGeometry& g = Geometry(h);
  vasl::render::RenderRequest request;
  request.pose = Site().NovelViews()[0];
  request.width_px = width_px;
  request.height_px = width_px / 2;
  const vasl::records::FusedValues none;
  int64_t hits = 0;
  uint32_t fnv = 2166136261u;
  for (auto _ : state) {
    auto image = vasl::render::RenderEquirect(g, none, request);
    if (!image.ok()) {
      state.SkipWithError(image.status().ToString().c_str());
      return;
    }
    hits = image->hit_pixels;
    benchmark::DoNotOptimize(image->depth_m.data());
    state.PauseTiming();
    fnv = 2166136261u;
    for (const std::vector<float>* a : {&image->depth_m, &image->normal}) {
      const auto* bytes = reinterpret_cast<const unsigned char*>(a->data());
      for (size_t i = 0; i < a->size() * sizeof(float); ++i) fnv = (fnv ^ bytes[i]) * 16777619u;
    }
    state.ResumeTiming();
  }
  state.SetItemsProcessed(int64_t(state.iterations()) * width_px * (width_px / 2));
  state.counters["vossels"] = double(g.size());
  state.counters["hit_pixels"] = double(hits);
  state.counters["image_fnv"] = double(fnv);
}

/// The march's W×W/2 image at h = 2 cm coloured as a render of the site shows it: the site's
/// albedo where a ray hits (linear, textured), off by up to ±3% per 2 cm vossel, black and
/// uncovered where it misses. Built once.
const vasl::render::RenderImage& ColouredRender(int width_px) {
  static std::map<int, vasl::render::RenderImage> by_width;
  static std::mutex mu;
  std::lock_guard<std::mutex> lock(mu);
  if (auto it = by_width.find(width_px); it != by_width.end()) return it->second;
  vasl::render::RenderRequest request;
  request.pose = Site().NovelViews()[0];
  request.width_px = width_px;
  request.height_px = width_px / 2;
  auto image = vasl::render::RenderEquirect(Geometry(0.02), vasl::records::FusedValues{}, request);
  if (!image.ok()) {
    std::fprintf(stderr, "render: %s\n", image.status().ToString().c_str());
    std::exit(1);
  }
  const size_t n = image->depth_m.size();
  image->rgb.assign(3 * n, 0.0f);
  image->alpha.assign(n, 0.0f);
  image->uncertainty.assign(n, 0.0f);
  const vasl::geometry::EquirectSize size{image->width_px, image->height_px};
  for (size_t p = 0; p < n; ++p) {
    if (!std::isfinite(image->depth_m[p])) continue;
    const Eigen::Vector3d d_world =
        request.pose.q_world_sensor *
        vasl::geometry::EquirectUnproject(double(p % size_t(size.width_px)) + 0.5,
                                          double(p / size_t(size.width_px)) + 0.5, size);
    const vasl::scenes::SceneHit hit = Site().Intersect(request.pose.o_world, d_world, 1000.0);
    if (!hit.valid) continue;
    const Eigen::Vector3f albedo = Site().Albedo(hit.x_world, hit.face);
    // A fused vossel's colour: the albedo at its centre, off by up to ±3% per vossel and
    // channel as a capture's noise leaves it (a fixed hash of the vossel's coordinates).
    const Eigen::Vector3i cell = (hit.x_world / 0.02).array().floor().cast<int>();
    for (int c = 0; c < 3; ++c) {
      const uint32_t hash = (uint32_t(cell.x()) * 73856093u) ^ (uint32_t(cell.y()) * 19349663u) ^
                            (uint32_t(cell.z()) * 83492791u) ^ (uint32_t(c) * 2654435761u);
      const uint32_t mixed = hash * 2654435761u;
      image->rgb[3 * p + c] = albedo[c] * (0.97f + 0.06f * float(mixed >> 8) / float(1u << 24));
    }
    image->alpha[p] = 1.0f;
    image->uncertainty[p] = 0.01f;
  }
  return by_width.emplace(width_px, std::move(*image)).first->second;
}

/// A render's file made from its image, whole (render::Encode: the rows a streamed render
/// encodes as they finish, all at once). Items are pixels; bytes the file's.
void BM_Encode(benchmark::State& state, vasl::render::ImageFormat format, int width_px) {
  const vasl::render::RenderImage& image = ColouredRender(width_px);
  size_t bytes = 0;
  for (auto _ : state) {
    auto file = vasl::render::Encode(format, image);
    if (!file.ok()) {
      state.SkipWithError(file.status().ToString().c_str());
      return;
    }
    bytes = file->size();
    benchmark::DoNotOptimize(file->data());
  }
  state.SetItemsProcessed(int64_t(state.iterations()) * width_px * (width_px / 2));
  state.counters["file_MB"] = double(bytes) / 1e6;
}

BENCHMARK_CAPTURE(BM_DepthPanorama, camera_station_12, 11, kCameraPitchRad, kCameraDivergenceRad)
    ->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK_CAPTURE(BM_DepthPanorama, camera_station_2, 1, kCameraPitchRad, kCameraDivergenceRad)
    ->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK_CAPTURE(BM_DepthPanorama, lidar_station_12, 11, kLidarPitchRad, kLidarDivergenceRad)
    ->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK_CAPTURE(BM_Dilate, camera_station_12, 11)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK_CAPTURE(BM_Visibility, camera_station_12, 11, kCameraPitchRad, kCameraDivergenceRad, 3)
    ->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK_CAPTURE(BM_Visibility, lidar_station_12, 11, kLidarPitchRad, kLidarDivergenceRad, 1)
    ->Unit(benchmark::kMillisecond)->UseRealTime();

BENCHMARK_CAPTURE(BM_Render, h5cm_2048, 0.05, 2048)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK_CAPTURE(BM_Render, h2cm_2048, 0.02, 2048)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK_CAPTURE(BM_Render, h2cm_4096, 0.02, 4096)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK_CAPTURE(BM_Encode, png_4096, vasl::render::ImageFormat::kPng, 4096)
    ->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK_CAPTURE(BM_Encode, exr_4096, vasl::render::ImageFormat::kExr, 4096)
    ->Unit(benchmark::kMillisecond)->UseRealTime();

}  // namespace

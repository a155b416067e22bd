// The §9 camera kernels every camera's load runs (at ingest, and again on each revisit that does
// not find the image in the revisit cache), under Google Benchmark (deploy/bench.sh): the PNG
// decode, the artefact detectors together (DetectArtefacts) and the chromatic fringing estimate
// alone, on the corridor's panorama from station 2 at the realistic site's 4096×2048 (items are
// pixels); and the calibration check's patch search (ingest::internal::CorrelationGrid, §2.3) at
// its default 15×15 template over 17×17 shifts (items are shifts).
#include <cstdio>
#include <cstdlib>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include <benchmark/benchmark.h>

#include "lattice/ingest/artefacts.h"
#include "lattice/ingest/calibration.h"
#include "lattice/ingest/sources.h"
#include "lattice/memory/isa.h"
#include "tests/scenes/corridor_site.h"

namespace {

constexpr int kWidthPx = 4096, kHeightPx = 2048;
constexpr int64_t kMaxPixels = int64_t{1} << 26;

/// The panorama's PNG bytes, rendered as the realistic site renders them (supersample 2).
const std::string& Png() {
  static const std::string png = [] {
    const vasl::scenes::CorridorSite site = vasl::scenes::CorridorSite::Default();
    const vasl::scenes::Panorama pano = vasl::scenes::RenderPanorama(
        site, vasl::scenes::CameraPoseForStation(site.Stations()[1]), kWidthPx, kHeightPx, 2);
    absl::StatusOr<std::string> bytes = vasl::scenes::EncodePng(pano);
    if (!bytes.ok()) {
      std::fprintf(stderr, "panorama: %s\n", bytes.status().ToString().c_str());
      std::exit(1);
    }
    return *bytes;
  }();
  return png;
}

/// The panorama as a camera's load decodes it.
const vasl::geometry::LinearImage& Decoded() {
  static const vasl::geometry::LinearImage image = [] {
    absl::StatusOr<vasl::geometry::LinearImage> decoded =
        vasl::ingest::DecodeImage(Png(), /*single_channel=*/false, kMaxPixels);
    if (!decoded.ok()) {
      std::fprintf(stderr, "decode: %s\n", decoded.status().ToString().c_str());
      std::exit(1);
    }
    return std::move(*decoded);
  }();
  return image;
}

void BM_DecodePng(benchmark::State& state) {
  Png();
  for (auto _ : state) {
    benchmark::DoNotOptimize(vasl::ingest::DecodeImage(Png(), false, kMaxPixels));
  }
  state.SetItemsProcessed(state.iterations() * int64_t(kWidthPx) * kHeightPx);
}

void BM_DetectArtefacts(benchmark::State& state) {
  Decoded();
  for (auto _ : state) {
    benchmark::DoNotOptimize(vasl::ingest::DetectArtefacts(Decoded(), /*wrap=*/true));
  }
  state.SetItemsProcessed(state.iterations() * int64_t(kWidthPx) * kHeightPx);
}

void BM_EstimateChannelShift(benchmark::State& state) {
  Decoded();
  for (auto _ : state) {
    benchmark::DoNotOptimize(vasl::ingest::EstimateChannelShift(Decoded(), /*wrap=*/true));
  }
  state.SetItemsProcessed(state.iterations() * int64_t(kWidthPx) * kHeightPx);
}

/// CorrelationGrid over 64 windows of random values (`holes_percent` of their cells empty, as a
/// LiDAR image's are), under instruction set `isa` at most.
void BM_CorrelationGrid(benchmark::State& state, int holes_percent, vasl::memory::Isa isa) {
  if (!vasl::memory::Supports(isa)) {
    state.SkipWithError("this CPU does not run that instruction set");
    return;
  }
  constexpr int kR = 7, kS = 8, kWindows = 64;
  constexpr int kPatch = 2 * kR + 1, kSpan = 2 * (kR + kS) + 1;
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> u(0.0f, 1.0f);
  std::vector<float> templ(size_t(kPatch) * kPatch);
  for (float& t : templ) t = u(rng);
  std::vector<std::vector<float>> windows(kWindows, std::vector<float>(size_t(kSpan) * kSpan));
  for (std::vector<float>& w : windows) {
    for (float& v : w) {
      v = u(rng) * 100.0f < float(holes_percent) ? std::numeric_limits<float>::quiet_NaN() : u(rng);
    }
  }
  vasl::memory::SetIsaCap(isa);
  size_t k = 0;
  for (auto _ : state) {
    benchmark::DoNotOptimize(vasl::ingest::internal::CorrelationGrid(
        templ, windows[k++ % kWindows], kR, kS, templ.size() / 2));
  }
  vasl::memory::SetIsaCap(vasl::memory::Isa::kX86_64_V4);
  state.SetItemsProcessed(state.iterations() * int64_t(2 * kS + 1) * (2 * kS + 1));
}

}  // namespace

BENCHMARK(BM_DecodePng)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_DetectArtefacts)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_EstimateChannelShift)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK_CAPTURE(BM_CorrelationGrid, whole_baseline, 0, vasl::memory::Isa::kBaseline)
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_CorrelationGrid, whole_avx2, 0, vasl::memory::Isa::kAvx2)
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_CorrelationGrid, holes5_baseline, 5, vasl::memory::Isa::kBaseline)
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_CorrelationGrid, holes5_avx2, 5, vasl::memory::Isa::kAvx2)
    ->Unit(benchmark::kMicrosecond);

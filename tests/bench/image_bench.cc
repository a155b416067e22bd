// The §9 camera kernels every camera's load runs (at ingest, and again on each revisit that does
// not find the image in the revisit cache), under Google Benchmark (deploy/bench.sh): the PNG
// decode, the artefact detectors together (DetectArtefacts) and the chromatic fringing estimate
// alone, on the corridor's panorama from station 2 at the realistic site's 4096×2048 (items are
// pixels).
#include <cstdio>
#include <cstdlib>
#include <string>

#include <benchmark/benchmark.h>

#include "lattice/ingest/artefacts.h"
#include "lattice/ingest/sources.h"
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

}  // namespace

BENCHMARK(BM_DecodePng)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_DetectArtefacts)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_EstimateChannelShift)->Unit(benchmark::kMillisecond)->UseRealTime();

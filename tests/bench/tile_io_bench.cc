// vasl_kernels_bench: encoding and reading one tile's objects (README "Storage"), what every
// commit and every reweight from disk does once per tile it writes or reads. The tile is the
// fullest of a real store: the first three scans of the corridor site (h 5 cm, tiles of 64
// vossels) ingested through the engine into a temporary directory.
// Run by deploy/bench.sh; figures, not pass/fail tests.
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <map>
#include <string>
#include <system_error>

#include <benchmark/benchmark.h>

#include "lattice/engine.h"
#include "lattice/records/record_grid.h"
#include "lattice/store/project_store.h"
#include "tests/scenes/corridor_site.h"
#include "tests/scenes/synthetic_scene.h"

namespace {

namespace fs = std::filesystem;

/// One tile of a stored project: its object files and what they hold.
struct Tile {
  fs::path dir;  ///< the store, removed at exit
  fs::path geometry_path, records_path, fused_path;
  vasl::records::VosselGeometry geometry;  ///< with its sums and frames (ReadGeometry)
  vasl::records::VosselGeometry lattice;   ///< the index grid alone (ReadLattice)
  vasl::records::RecordSet records;
  vasl::records::FusedValues fused;
};

[[noreturn]] void Die(const absl::Status& s) {
  std::fprintf(stderr, "tile_io_bench: %s\n", s.ToString().c_str());
  std::exit(1);
}

const Tile& TheTile() {
  static const Tile tile = [] {
    using namespace vasl;
    const fs::path dir =
        fs::temp_directory_path() / ("vasl-tile-io-bench-" + std::to_string(::getpid()));
    fs::remove_all(dir);
    auto engine = Engine::Open(dir, EngineLimits{});
    if (!engine.ok()) Die(engine.status());
    store::ProjectSettings settings;
    settings.vossel_size_m = 0.05;
    settings.tile_vossels = 64;
    if (auto p = (*engine)->CreateProject("tiles", settings); !p.ok()) Die(p.status());
    const scenes::CorridorSite site = scenes::CorridorSite::Default();
    scenes::LidarSettings lidar;
    lidar.azimuth_steps = 1440;
    lidar.elevation_steps = 720;
    for (size_t n = 0; n < 3; ++n) {
      lidar.seed = uint64_t(n + 1);
      auto scan = scenes::MakeScanInput(site, n, lidar, 2048, 2);
      if (!scan.ok()) Die(scan.status());
      if (auto r = (*engine)->IngestScan("tiles", *scan); !r.ok()) Die(r.status());
    }
    auto st = store::ProjectStore::Open(dir / "tiles");
    if (!st.ok()) Die(st.status());
    auto manifest = (*st)->LoadManifest((*st)->head_version());
    if (!manifest.ok()) Die(manifest.status());
    const std::map<std::string, store::ManifestEntry>* fullest = nullptr;
    for (const auto& [key, layers] : manifest->tiles) {
      auto it = layers.find(store::kLayerRecords);
      if (it == layers.end()) continue;
      if (fullest == nullptr || it->second.records > fullest->at(store::kLayerRecords).records) {
        fullest = &layers;
      }
    }
    if (fullest == nullptr) Die(absl::InternalError("the store has no tile with records"));
    const auto path_of = [&](const std::string& layer) {
      auto p = (*st)->objects().LocalPath(fullest->at(layer).object);
      if (!p.ok()) Die(p.status());
      return *p;
    };
    Tile t;
    t.dir = dir;
    t.geometry_path = path_of(store::kLayerGeometry);
    t.records_path = path_of(store::kLayerRecords);
    t.fused_path = path_of(store::kLayerFusedDefault);
    auto g = records::ReadGeometry(t.geometry_path);
    auto l = records::ReadLattice(t.geometry_path);
    if (!g.ok()) Die(g.status());
    if (!l.ok()) Die(l.status());
    t.geometry = std::move(*g);
    t.lattice = std::move(*l);
    auto recs = records::ReadRecords(t.lattice, t.records_path);
    if (!recs.ok()) Die(recs.status());
    t.records = std::move(*recs);
    auto fused = records::ReadFused(t.lattice, t.fused_path);
    if (!fused.ok()) Die(fused.status());
    t.fused = std::move(*fused);
    std::printf("tile_io_bench: tile of %zu vossels, %zu records; objects %.2f MB geometry, "
                "%.2f MB records, %.2f MB fused\n",
                t.geometry.size(), t.records.size(), fs::file_size(t.geometry_path) / 1e6,
                fs::file_size(t.records_path) / 1e6, fs::file_size(t.fused_path) / 1e6);
    return t;
  }();
  static const struct RemoveAtExit {  // the store goes with the process
    const Tile& t;
    ~RemoveAtExit() {
      std::error_code ec;
      fs::remove_all(t.dir, ec);
    }
  } remove_at_exit{tile};
  return tile;
}

template <typename Fn>
void Run(benchmark::State& state, const fs::path& file, Fn&& fn) {
  const Tile& t = TheTile();
  for (auto _ : state) {
    auto r = fn(t);
    if (!r.ok()) {
      state.SkipWithError(std::string(r.status().message()).c_str());
      return;
    }
    benchmark::DoNotOptimize(r);
  }
  state.SetItemsProcessed(int64_t(state.iterations()) * int64_t(t.geometry.size()));
  state.SetBytesProcessed(int64_t(state.iterations()) * int64_t(fs::file_size(file)));
}

void BM_EncodeGeometry(benchmark::State& state) {
  Run(state, TheTile().geometry_path,
      [](const Tile& t) { return vasl::records::EncodeGeometry(t.geometry); });
}
void BM_EncodeRecords(benchmark::State& state) {
  Run(state, TheTile().records_path,
      [](const Tile& t) { return vasl::records::EncodeRecords(t.lattice, t.records); });
}
void BM_EncodeFused(benchmark::State& state) {
  Run(state, TheTile().fused_path,
      [](const Tile& t) { return vasl::records::EncodeFused(t.lattice, t.fused); });
}
void BM_ReadGeometry(benchmark::State& state) {
  Run(state, TheTile().geometry_path,
      [](const Tile& t) { return vasl::records::ReadGeometry(t.geometry_path); });
}
void BM_ReadLattice(benchmark::State& state) {
  Run(state, TheTile().geometry_path,
      [](const Tile& t) { return vasl::records::ReadLattice(t.geometry_path); });
}
void BM_ReadRecords(benchmark::State& state) {
  Run(state, TheTile().records_path,
      [](const Tile& t) { return vasl::records::ReadRecords(t.lattice, t.records_path); });
}
void BM_ReadFused(benchmark::State& state) {
  Run(state, TheTile().fused_path,
      [](const Tile& t) { return vasl::records::ReadFused(t.lattice, t.fused_path); });
}

}  // namespace

// Items are the tile's vossels, bytes its object's size.
BENCHMARK(BM_EncodeGeometry)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_EncodeRecords)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_EncodeFused)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_ReadGeometry)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_ReadLattice)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_ReadRecords)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_ReadFused)->Unit(benchmark::kMillisecond)->UseRealTime();

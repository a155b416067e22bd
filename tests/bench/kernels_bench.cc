// vasl_kernels_bench: Google Benchmark figures of the hot kernels on this machine's cores (issue
// "Speed"): the §7 weight kernel and fusion over records in memory, under the multiply-only
// profile (exponents 0/1/2) and under general exponents with proximity, beside a STREAM-style
// triad that measures the memory bandwidth the record passes are held against.
// Run by deploy/bench.sh; figures, not pass/fail tests.
#include <algorithm>
#include <cstdint>
#include <optional>
#include <random>
#include <vector>

#include <benchmark/benchmark.h>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include "lattice/fusion/fuse.h"
#include "lattice/fusion/weight.h"
#include "lattice/geometry/footprint.h"

namespace {

using vasl::records::RecordSet;
constexpr double kVosselM = 0.02;
constexpr size_t kRecords = size_t(1) << 22;  // 4 M records: ~300 MB, far past the caches
constexpr size_t kPerVossel = 8;              // records per vossel, as on the bench room

/// Bytes of record columns a weight pass reads per record (vis, cos, footprint, conf, scan,
/// flags, range) and writes (the weight).
constexpr double kWeightBytes = 4 + 4 + 8 + 4 * vasl::records::kConfidenceCount + 4 + 1 + 4 + 4;

/// Records as ingest makes them: sorted by vossel, LiDAR and RGB, values in their ranges.
const RecordSet& Records() {
  static const RecordSet records = [] {
    RecordSet r;
    r.Resize(kRecords);
    std::mt19937 rng(7);
    std::uniform_real_distribution<float> u(0.0f, 1.0f);
    for (size_t i = 0; i < kRecords; ++i) {
      r.vossel[i] = int32_t(i / kPerVossel);
      r.scan[i] = int32_t(1 + i % kPerVossel);
      const bool rgb = (i % 2) != 0;
      r.modality[i] = int8_t(rgb ? vasl::records::Modality::kRgb : vasl::records::Modality::kLidar);
      for (int c = 0; c < vasl::records::kValueChannels; ++c) r.value[3 * i + c] = u(rng);
      r.range_m[i] = 1.0f + 20.0f * u(rng);
      r.cos_inc[i] = 0.05f + 0.95f * u(rng);
      r.foot_major_m[i] = 0.002f + 0.03f * u(rng);
      r.foot_minor_m[i] = r.foot_major_m[i] * (0.5f + 0.5f * u(rng));
      r.uv_px[2 * i] = 100.0f * u(rng);
      r.uv_px[2 * i + 1] = 100.0f * u(rng);
      r.vis[i] = u(rng) < 0.9f ? 1.0f : u(rng);
      for (int f = 0; f < vasl::records::kConfidenceCount; ++f) {
        r.conf[i * vasl::records::kConfidenceCount + f] = u(rng) < 0.8f ? 1.0f : u(rng);
      }
      r.flags[i] = 0;
      r.batch[i] = 1;
    }
    return r;
  }();
  return records;
}
size_t VosselCount() { return (kRecords + kPerVossel - 1) / kPerVossel; }

/// Exponents 0/1/2 only: every factor multiplies (the ceiling the general profile is held to).
vasl::fusion::WeightingProfile MultiplyOnly() { return vasl::fusion::WeightingProfile{}; }
/// General exponents on every factor: one exp of a sum of logs.
vasl::fusion::WeightingProfile GeneralExponents() {
  vasl::fusion::WeightingProfile p;
  p.alpha = 1.3;
  p.beta = 0.7;
  p.rho = 0.5;
  p.kappa = {2.5, 1.5, 0.5, 1.2, 0.8, 1.7};
  return p;
}
/// The same with the proximity term (r_{k,min} per vossel and channel).
vasl::fusion::WeightingProfile General() {
  vasl::fusion::WeightingProfile p;
  p.alpha = 1.3;
  p.beta = 0.7;
  p.rho = 0.5;
  p.kappa = {2.5, 1.5, 0.5, 1.2, 0.8, 1.7};
  p.proximity_m = 2.0;
  return p;
}

void Report(benchmark::State& state, double bytes_per_record) {
  state.SetItemsProcessed(int64_t(state.iterations()) * int64_t(kRecords));
  state.SetBytesProcessed(int64_t(double(state.iterations()) * kRecords * bytes_per_record));
}

/// The kernel alone, one thread, records in memory (no offsets, no r_min: the proximity term
/// reads r as its own minimum), by the widest variant the CPU runs, or by `isa`'s.
void BM_WeightKernelOneThread(benchmark::State& state, vasl::fusion::WeightingProfile p,
                              std::optional<vasl::fusion::WeightKernel::Isa> isa = std::nullopt) {
  if (isa && !vasl::memory::Supports(*isa)) {
    state.SkipWithError("this CPU does not run that instruction set");
    return;
  }
  const RecordSet& r = Records();
  const vasl::fusion::WeightKernel kernel(p, vasl::geometry::TargetResolutionM(kVosselM));
  std::vector<float> w(r.size());
  vasl::fusion::WeightColumns c = vasl::fusion::WeightColumns::Of(r);
  c.range_min_m = r.range_m.data();
  for (auto _ : state) {
    if (isa) {
      kernel.EvaluateOn(*isa, c, r.size(), w.data());
    } else {
      kernel.Evaluate(c, r.size(), w.data());
    }
    benchmark::DoNotOptimize(w.data());
  }
  Report(state, kWeightBytes);
}

/// RecordWeights: offsets, r_min per vossel and channel, and the kernel, on every core.
void BM_RecordWeights(benchmark::State& state, vasl::fusion::WeightingProfile p) {
  const RecordSet& r = Records();
  for (auto _ : state) {
    auto w = vasl::fusion::RecordWeights(r, VosselCount(), kVosselM, p);
    if (!w.ok()) state.SkipWithError(w.status().ToString().c_str());
    benchmark::DoNotOptimize(w->weight.data());
  }
  Report(state, kWeightBytes + 4);
}

/// Fuse: the weights and the weighted means and uncertainties of every vossel, on every core.
void BM_Fuse(benchmark::State& state, vasl::fusion::WeightingProfile p) {
  const RecordSet& r = Records();
  for (auto _ : state) {
    auto f = vasl::fusion::Fuse(r, VosselCount(), kVosselM, p);
    if (!f.ok()) state.SkipWithError(f.status().ToString().c_str());
    benchmark::DoNotOptimize(&*f);
  }
  Report(state, kWeightBytes + 4 + 1 + 12);
}

/// MergeRenumbered as an ingest calls it: a project's records kept (a tenth left out, as
/// revisited or vanished), their vossels renumbered around the vossels that appeared (one new
/// vossel after every eighth), merged with 2% new records; each record copied once.
void BM_MergeRenumbered(benchmark::State& state) {
  const RecordSet& r = Records();
  std::vector<size_t> rows;
  rows.reserve(r.size());
  for (size_t i = 0; i < r.size(); ++i) {
    if (i % 10 != 3) rows.push_back(i);
  }
  std::vector<int32_t> renumber(VosselCount());
  for (size_t v = 0; v < renumber.size(); ++v) renumber[v] = int32_t(v + v / 8);
  RecordSet added;
  {
    std::vector<size_t> some;
    for (size_t i = 0; i < r.size(); i += 50) some.push_back(i);
    added = r.Select(some);
    for (size_t i = 0; i < added.size(); ++i) {
      added.vossel[i] = renumber[size_t(added.vossel[i])] + int32_t(i % 2);  // old and new
      added.scan[i] = 100;
    }
  }
  for (auto _ : state) {
    RecordSet merged = vasl::records::MergeRenumbered(r, rows, renumber, added);
    benchmark::DoNotOptimize(merged.vossel.data());
  }
  state.SetItemsProcessed(int64_t(state.iterations()) * int64_t(rows.size() + added.size()));
}

/// STREAM triad a = b + s·c over 3 × 64 MB of doubles on every core: the memory bandwidth of
/// this machine in this run (bytes moved, counting the write once).
void BM_Triad(benchmark::State& state) {
  const size_t n = size_t(8) << 20;
  std::vector<double> a(n, 0.0), b(n, 1.0), c(n, 2.0);
  for (auto _ : state) {
    tbb::parallel_for(tbb::blocked_range<size_t>(0, n, 1 << 16),
                      [&](const tbb::blocked_range<size_t>& range) {
      for (size_t i = range.begin(); i != range.end(); ++i) a[i] = b[i] + 3.0 * c[i];
    });
    benchmark::DoNotOptimize(a.data());
  }
  state.SetBytesProcessed(int64_t(state.iterations()) * int64_t(3 * n * sizeof(double)));
}

}  // namespace

BENCHMARK_CAPTURE(BM_WeightKernelOneThread, multiply_only, MultiplyOnly())
    ->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK_CAPTURE(BM_WeightKernelOneThread, general, General())
    ->Unit(benchmark::kMillisecond)->UseRealTime();
// Each instruction set's variant of the general kernel (the same bits from each).
BENCHMARK_CAPTURE(BM_WeightKernelOneThread, general_baseline, General(),
                  vasl::fusion::WeightKernel::Isa::kBaseline)
    ->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK_CAPTURE(BM_WeightKernelOneThread, general_avx2, General(),
                  vasl::fusion::WeightKernel::Isa::kAvx2)
    ->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK_CAPTURE(BM_WeightKernelOneThread, general_x86_64_v4, General(),
                  vasl::fusion::WeightKernel::Isa::kX86_64_V4)
    ->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK_CAPTURE(BM_RecordWeights, multiply_only, MultiplyOnly())
    ->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK_CAPTURE(BM_RecordWeights, general_exponents, GeneralExponents())
    ->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK_CAPTURE(BM_RecordWeights, general, General())
    ->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK_CAPTURE(BM_Fuse, multiply_only, MultiplyOnly())
    ->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK_CAPTURE(BM_Fuse, general_exponents, GeneralExponents())
    ->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK_CAPTURE(BM_Fuse, general, General())->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_MergeRenumbered)->Unit(benchmark::kMillisecond)->UseRealTime();
BENCHMARK(BM_Triad)->Unit(benchmark::kMillisecond)->UseRealTime();

BENCHMARK_MAIN();

#include "lattice/fusion/fuse.h"

#include <algorithm>
#include <atomic>
#include <cctype>
#include <cmath>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_reduce.h>

#include "absl/strings/str_cat.h"
#include "lattice/fusion/weight.h"
#include "lattice/geometry/footprint.h"
#include "lattice/memory/huge_pages.h"

namespace vasl::fusion {

using records::Modality;

absl::Status ValidateProfile(const WeightingProfile& p) {
  const auto bad = [&p](const char* what) {
    return absl::InvalidArgumentError(
        absl::StrCat("weighting profile '", p.name, "': ", what));
  };
  for (double e : {p.alpha, p.beta, p.rho, p.lambda_src, p.theta_max_rad, p.proximity_m}) {
    if (!std::isfinite(e) || e < 0.0) return bad("exponents, λ_src, θ_max and ρ_p must be finite and ≥ 0");
  }
  for (double k : p.kappa) {
    if (!std::isfinite(k) || k < 0.0) return bad("confidence exponents κ must be finite and ≥ 0");
  }
  if (!(p.v_min >= 0.0 && p.v_min <= 1.0)) return bad("V_min must lie in [0, 1]");
  for (const auto& [scan, g] : p.scan_gain) {
    if (!std::isfinite(g) || g < 0.0) return bad("scan gains g_m must be finite and ≥ 0");
  }
  for (const auto& [scan, a] : p.channel_gain) {
    for (double g : a) {
      if (!std::isfinite(g) || g <= 0.0) return bad("channel gains a_{m,c} must be finite and > 0");
    }
  }
  for (int64_t id : p.lens_maps) {
    if (id <= 0) return bad("lens map ids must be > 0");
  }
  if (p.name.empty() || p.name.size() > 63) return bad("the name must have 1 to 63 characters");
  for (char ch : p.name) {
    if (!(std::isalnum(static_cast<unsigned char>(ch)) || ch == '-' || ch == '_' || ch == '.')) {
      return bad("the name may hold only letters, digits, '-', '_' and '.'");
    }
  }
  return absl::OkStatus();
}

std::vector<std::array<float, records::kValueChannels>> DenseChannelGains(
    const WeightingProfile& profile, const records::RecordSet& recs) {
  int32_t max_id = tbb::parallel_reduce(
      tbb::blocked_range<size_t>(0, recs.size(), 1 << 16), int32_t(0),
      [&recs](const tbb::blocked_range<size_t>& r, int32_t m) {
        for (size_t i = r.begin(); i != r.end(); ++i) m = std::max(m, recs.scan[i]);
        return m;
      },
      [](int32_t a, int32_t b) { return std::max(a, b); });
  for (const auto& [s, a] : profile.channel_gain) max_id = std::max(max_id, s);
  std::vector<std::array<float, records::kValueChannels>> out(size_t(max_id) + 1);
  for (auto& a : out) a.fill(1.0f);
  for (const auto& [s, a] : profile.channel_gain) {
    if (s < 0) continue;
    for (int c = 0; c < records::kValueChannels; ++c) out[size_t(s)][c] = float(a[c]);
  }
  return out;
}

absl::StatusOr<RecordValues> RecordValues::Of(const WeightingProfile& profile,
                                              const records::RecordSet& recs) {
  if (!profile.lens_maps.empty() && profile.lens == nullptr) {
    return absl::FailedPreconditionError(absl::StrCat(
        "weighting profile '", profile.name, "' applies lens maps that were not loaded"));
  }
  RecordValues out(recs);
  out.gain_ = DenseChannelGains(profile, recs);
  out.lens_.assign(out.gain_.size(), {nullptr, nullptr});
  if (profile.lens != nullptr) {
    for (const auto& [source, index] : profile.lens->by_source) {
      if (source >= 0 && size_t(source) < out.lens_.size()) {
        const LensMap* map = profile.lens->maps[index].get();
        out.lens_[size_t(source)] = {map, &map->source_gain.at(source)};
        out.has_lens_ = true;
      }
    }
  }
  return out;
}

LensFactors RecordValues::AdjustThroughLens(size_t i, float* v) const {
  const auto& [map, gain] = lens_[size_t(recs_->scan[i])];
  std::copy_n(&recs_->value[i * records::kValueChannels], records::kValueChannels, v);
  return AdjustForLens(*map, *gain, &recs_->uv_px[2 * i], v);
}

void RecordValues::CorrectImageSample(int32_t source, const float* uv, float* value) const {
  if (source < 0 || size_t(source) >= lens_.size() || lens_[size_t(source)].first == nullptr) {
    return;
  }
  const auto& [map, gain] = lens_[size_t(source)];
  AdjustForLens(*map, *gain, uv, value);
}

LensFactors RecordValues::LensConfidence(size_t i) const {
  const int32_t s = recs_->scan[i];
  if (s < 0 || lens_[size_t(s)].first == nullptr) return {};
  double value[records::kValueChannels];
  return Read(i, value);
}

absl::StatusOr<std::vector<size_t>> VosselOffsets(const records::RecordSet& recs,
                                                  size_t vossel_count) {
  // Records sorted by vossel: begin[k] is the first record whose vossel is ≥ k, written by
  // the one record where the vossel index steps past k, so that record chunks fill it apart.
  const size_t n = recs.size();
  std::vector<size_t> begin;
  memory::AssignOnHugePages(begin, vossel_count + 1, size_t(0));
  std::atomic<bool> sorted{true};
  tbb::parallel_for(tbb::blocked_range<size_t>(0, n, 1 << 16),
                    [&](const tbb::blocked_range<size_t>& r) {
    int64_t previous = r.begin() == 0 ? -1 : int64_t(recs.vossel[r.begin() - 1]);
    for (size_t i = r.begin(); i != r.end(); ++i) {
      const int64_t k = recs.vossel[i];
      if (k < 0 || k < previous || k >= int64_t(vossel_count)) {
        sorted = false;
        return;
      }
      for (int64_t j = previous + 1; j <= k; ++j) begin[size_t(j)] = i;
      previous = k;
    }
  });
  if (!sorted) return absl::InternalError("records are not sorted by a valid vossel index");
  for (size_t k = n == 0 ? 0 : size_t(recs.vossel[n - 1]) + 1; k <= vossel_count; ++k) {
    begin[k] = n;
  }
  return begin;
}

namespace {

/// w_{k,m} of the records of vossels [k_begin, k_end) into w[0, begin[k_end] − begin[k_begin]):
/// r_{k,min} per vossel and fused channel when the profile has the proximity term, the §9 lens
/// factors of conf[dirt] and conf[fog] when it applies lens maps, then the kernel.
void WeighVossels(const records::RecordSet& recs, const std::vector<size_t>& begin,
                  size_t k_begin, size_t k_end, const WeightKernel& kernel,
                  const RecordValues& values, float* w) {
  constexpr int kF = records::kConfidenceCount;
  thread_local std::vector<float> range_min, conf;
  const size_t first = begin[k_begin], end = begin[k_end];
  WeightColumns columns = WeightColumns::Of(recs, first);
  if (kernel.uses_range_min()) {
    range_min.resize(end - first);
    for (size_t k = k_begin; k != k_end; ++k) {
      const size_t b = begin[k], e = begin[k + 1];
      float lowest[records::kModalityCount];
      std::fill(std::begin(lowest), std::end(lowest), HUGE_VALF);
      for (size_t i = b; i < e; ++i) {  // every channel's minimum updated by select, in registers
        const int c = int(FusedChannelOf(Modality(recs.modality[i])));
        const float r = recs.range_m[i];
        for (int q = 0; q < records::kModalityCount; ++q) {
          lowest[q] = c == q ? std::min(lowest[q], r) : lowest[q];
        }
      }
      for (size_t i = b; i < e; ++i) {
        range_min[i - first] = lowest[int(FusedChannelOf(Modality(recs.modality[i])))];
      }
    }
    columns.range_min_m = range_min.data();
  }
  if (values.has_lens()) {
    conf.assign(&recs.conf[first * kF], &recs.conf[end * kF]);
    for (size_t i = first; i < end; ++i) {
      if (const LensFactors lens = values.LensConfidence(i); lens != LensFactors{}) {
        conf[(i - first) * kF + records::kConfDirt] *= lens.dirt;
        conf[(i - first) * kF + records::kConfFog] *= lens.fog;
      }
    }
    columns.conf = conf.data();
  }
  kernel.Evaluate(columns, end - first, w);
}

/// Vossels per task of the parallel passes over records (simple_partitioner: 512 to 1024), so
/// that a task's records, ~8 per vossel, and its scratch columns stay in L2.
constexpr size_t kVosselGrain = 1024;

/// The fused value, weight and uncertainty (§7) of vossels [k_begin, k_end) into `channel`
/// (per fused channel, null where no record has it) from their records' weights `w` (from the
/// first record of k_begin): the weighted mean, or the value of the heaviest record when
/// `kNearest`, and spread ⊕ 1/sqrt(Σw). A record whose weight is not > 0 (NaN too) takes no
/// part; a channel without one keeps no value. The sums of a channel start at 0 in every
/// vossel and the loop over records has no branch on the data but the nearest mode's.
template <bool kNearest>
void FuseVossels(const records::RecordSet& recs, const std::vector<size_t>& begin,
                 size_t k_begin, size_t k_end, const float* w, const RecordValues& values,
                 records::FusedModality* const* channel) {
  constexpr int kC = records::kValueChannels;
  struct Sums {
    double w, wc[kC], wcc[kC];
  } sums[records::kModalityCount];
  float best_w[records::kModalityCount];
  size_t best_i[records::kModalityCount];
  int fused[records::kModalityCount];  // the channels some record has (0 is not fused)
  int n = 0;
  for (int q = 1; q < records::kModalityCount; ++q) {
    if (channel[q] != nullptr) fused[n++] = q;
  }
  const size_t first = begin[k_begin];
  for (size_t k = k_begin; k != k_end; ++k) {
    sums[0] = Sums{};
    for (int j = 0; j < n; ++j) sums[fused[j]] = Sums{};
    if constexpr (kNearest) std::fill(std::begin(best_w), std::end(best_w), 0.0f);
    for (size_t i = begin[k], e = begin[k + 1]; i < e; ++i) {
      const float wi = w[i - first] > 0.0f ? w[i - first] : 0.0f;
      const int c = int(FusedChannelOf(Modality(recs.modality[i])));
      double v[kC];
      values.Read(i, v);
      // (A value the record's weight leaves out adds 0 too: NaN or ∞ times 0 would not.)
      for (int ch = 0; ch < kC; ++ch) v[ch] = wi > 0.0f ? v[ch] : 0.0;
      Sums& a = sums[c];
      const double wd = wi;
      a.w += wd;
      for (int ch = 0; ch < kC; ++ch) {
        a.wc[ch] += wd * v[ch];
        a.wcc[ch] += wd * v[ch] * v[ch];
      }
      if constexpr (kNearest) {
        if (wi > best_w[c]) {
          best_w[c] = wi;
          best_i[c] = i;
        }
      }
    }
    for (int j = 0; j < n; ++j) {
      const Sums& a = sums[fused[j]];
      if (!(a.w > 0.0)) continue;
      records::FusedModality& f = *channel[fused[j]];
      double variance = 0.0;
      double nearest[kC];
      if constexpr (kNearest) values.Read(best_i[fused[j]], nearest);
      for (int ch = 0; ch < f.channels; ++ch) {
        const double mean = a.wc[ch] / a.w;
        variance += std::max(0.0, a.wcc[ch] / a.w - mean * mean);
        f.value[k * f.channels + ch] = float(kNearest ? nearest[ch] : mean);
      }
      variance /= f.channels;
      f.weight[k] = float(a.w);
      f.uncertainty[k] = float(std::sqrt(variance + 1.0 / a.w));  // spread ⊕ 1/sqrt(Σw)
    }
  }
}

}  // namespace

absl::StatusOr<RecordWeightsResult> RecordWeights(const records::RecordSet& recs, size_t vossel_count,
                                                  double vossel_size_m, const WeightingProfile& profile) {
  if (absl::Status s = ValidateProfile(profile); !s.ok()) return s;
  auto begin = VosselOffsets(recs, vossel_count);
  if (!begin.ok()) return begin.status();
  RecordWeightsResult out;
  out.begin = std::move(*begin);
  memory::AssignOnHugePages(out.weight, recs.size(), 0.0f);
  absl::StatusOr<RecordValues> values = RecordValues::Of(profile, recs);
  if (!values.ok()) return values.status();
  const WeightKernel kernel(profile, geometry::TargetResolutionM(vossel_size_m));
  tbb::parallel_for(tbb::blocked_range<size_t>(0, vossel_count, kVosselGrain),
                    [&](const tbb::blocked_range<size_t>& r) {
    WeighVossels(recs, out.begin, r.begin(), r.end(), kernel, *values,
                 out.weight.data() + out.begin[r.begin()]);
  }, tbb::simple_partitioner());
  return out;
}

absl::StatusOr<records::FusedValues> Fuse(const records::RecordSet& recs, size_t vossel_count,
                                          double vossel_size_m, const WeightingProfile& profile) {
  if (absl::Status s = ValidateProfile(profile); !s.ok()) return s;
  const absl::StatusOr<std::vector<size_t>> offsets = VosselOffsets(recs, vossel_count);
  if (!offsets.ok()) return offsets.status();
  const std::vector<size_t>& begin = *offsets;
  const WeightKernel kernel(profile, geometry::TargetResolutionM(vossel_size_m));

  // The fused channels some record has, as a bit set over the records in parallel.
  const uint32_t present = tbb::parallel_reduce(
      tbb::blocked_range<size_t>(0, recs.size(), 1 << 16), uint32_t(0),
      [&recs](const tbb::blocked_range<size_t>& r, uint32_t bits) {
        for (size_t i = r.begin(); i != r.end(); ++i) {
          bits |= 1u << int(FusedChannelOf(Modality(recs.modality[i])));
        }
        return bits;
      },
      [](uint32_t a, uint32_t b) { return a | b; });
  records::FusedValues out;
  out.profile = profile.name;
  records::FusedModality* channel[records::kModalityCount] = {};
  for (int m = 1; m < records::kModalityCount; ++m) {
    if (!(present & (1u << m))) continue;
    records::FusedModality& f = out.by_modality[Modality(m)];
    f.channels = records::ChannelCount(Modality(m));
    memory::AssignOnHugePages(f.value, vossel_count * f.channels, 0.0f);
    memory::AssignOnHugePages(f.weight, vossel_count, 0.0f);
    memory::AssignOnHugePages(f.uncertainty, vossel_count, 0.0f);
    channel[m] = &f;
  }

  absl::StatusOr<RecordValues> values = RecordValues::Of(profile, recs);
  if (!values.ok()) return values.status();

  // One pass: each task weighs its vossels' records into a buffer it then reads, hot in cache.
  tbb::parallel_for(tbb::blocked_range<size_t>(0, vossel_count, kVosselGrain),
                    [&](const tbb::blocked_range<size_t>& range) {
    thread_local std::vector<float> weights;
    weights.resize(begin[range.end()] - begin[range.begin()]);
    WeighVossels(recs, begin, range.begin(), range.end(), kernel, *values, weights.data());
    if (profile.mode == FusionMode::kNearest) {
      FuseVossels<true>(recs, begin, range.begin(), range.end(), weights.data(), *values,
                        channel);
    } else {
      FuseVossels<false>(recs, begin, range.begin(), range.end(), weights.data(), *values,
                         channel);
    }
  }, tbb::simple_partitioner());
  return out;
}

}  // namespace vasl::fusion

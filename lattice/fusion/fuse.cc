#include "lattice/fusion/fuse.h"

#include <algorithm>
#include <cctype>
#include <cmath>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include "absl/strings/str_cat.h"
#include "lattice/fusion/weight.h"
#include "lattice/geometry/footprint.h"

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
  int32_t max_id = 0;
  for (int32_t s : recs.scan) max_id = std::max(max_id, s);
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
      }
    }
  }
  return out;
}

LensFactors RecordValues::Read(size_t i, double* out) const {
  const int32_t s = recs_->scan[i];
  float v[records::kValueChannels];
  std::copy_n(&recs_->value[i * records::kValueChannels], records::kValueChannels, v);
  LensFactors conf;
  if (s >= 0 && lens_[size_t(s)].first != nullptr) {
    const auto& [map, gain] = lens_[size_t(s)];
    conf = AdjustForLens(*map, *gain, &recs_->uv_px[2 * i], v);
  }
  for (int c = 0; c < records::kValueChannels; ++c) {
    out[c] = (s >= 0 ? double(gain_[size_t(s)][c]) : 1.0) * v[c];
  }
  return conf;
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
  std::vector<size_t> begin(vossel_count + 1, 0);
  for (size_t i = 0; i < recs.size(); ++i) {
    const int32_t k = recs.vossel[i];
    if (k < 0 || size_t(k) >= vossel_count || (i > 0 && recs.vossel[i - 1] > k)) {
      return absl::InternalError("records are not sorted by a valid vossel index");
    }
    ++begin[size_t(k) + 1];
  }
  for (size_t k = 0; k < vossel_count; ++k) begin[k + 1] += begin[k];
  return begin;
}

absl::StatusOr<RecordWeightsResult> RecordWeights(const records::RecordSet& recs, size_t vossel_count,
                                                  double vossel_size_m, const WeightingProfile& profile) {
  if (absl::Status s = ValidateProfile(profile); !s.ok()) return s;
  auto begin = VosselOffsets(recs, vossel_count);
  if (!begin.ok()) return begin.status();
  RecordWeightsResult out;
  out.begin = std::move(*begin);
  out.weight.assign(recs.size(), 0.0f);
  absl::StatusOr<RecordValues> values = RecordValues::Of(profile, recs);
  if (!values.ok()) return values.status();
  const double target_m = geometry::TargetResolutionM(vossel_size_m);
  tbb::parallel_for(tbb::blocked_range<size_t>(0, vossel_count, 1024),
                    [&](const tbb::blocked_range<size_t>& range) {
    for (size_t k = range.begin(); k != range.end(); ++k) {
      const size_t b = out.begin[k], e = out.begin[k + 1];
      double range_min[records::kModalityCount];
      std::fill(std::begin(range_min), std::end(range_min), HUGE_VAL);
      if (profile.proximity_m > 0.0) {
        for (size_t i = b; i < e; ++i) {
          const int c = int(FusedChannelOf(Modality(recs.modality[i])));
          range_min[c] = std::min(range_min[c], double(recs.range_m[i]));
        }
      }
      for (size_t i = b; i < e; ++i) {
        if (recs.flags[i] & records::kFlagInvalidated) continue;
        const int c = int(FusedChannelOf(Modality(recs.modality[i])));
        const auto g = profile.scan_gain.find(recs.scan[i]);
        WeightInputs in = WeightInputsOf(recs, i, float(range_min[c]));
        float conf[records::kConfidenceCount];
        if (const LensFactors lens = values->LensConfidence(i); lens != LensFactors{}) {  // §9
          std::copy(in.conf, in.conf + records::kConfidenceCount, conf);
          conf[records::kConfDirt] *= lens.dirt;
          conf[records::kConfFog] *= lens.fog;
          in.conf = conf;
        }
        out.weight[i] = float(RecordWeight(profile, in, target_m,
                                           g == profile.scan_gain.end() ? 1.0 : g->second));
      }
    }
  });
  return out;
}

absl::StatusOr<records::FusedValues> Fuse(const records::RecordSet& recs, size_t vossel_count,
                                          double vossel_size_m, const WeightingProfile& profile) {
  auto weights = RecordWeights(recs, vossel_count, vossel_size_m, profile);
  if (!weights.ok()) return weights.status();
  const std::vector<size_t>& begin = weights->begin;
  const std::vector<float>& weight = weights->weight;

  bool present[records::kModalityCount] = {};
  for (int8_t m : recs.modality) present[int(FusedChannelOf(Modality(m)))] = true;
  records::FusedValues out;
  out.profile = profile.name;
  records::FusedModality* channel[records::kModalityCount] = {};
  for (int m = 1; m < records::kModalityCount; ++m) {
    if (!present[m]) continue;
    records::FusedModality& f = out.by_modality[Modality(m)];
    f.channels = records::ChannelCount(Modality(m));
    f.value.assign(vossel_count * f.channels, 0.0f);
    f.weight.assign(vossel_count, 0.0f);
    f.uncertainty.assign(vossel_count, 0.0f);
    channel[m] = &f;
  }

  absl::StatusOr<RecordValues> values = RecordValues::Of(profile, recs);
  if (!values.ok()) return values.status();

  tbb::parallel_for(tbb::blocked_range<size_t>(0, vossel_count, 1024),
                    [&](const tbb::blocked_range<size_t>& range) {
    for (size_t k = range.begin(); k != range.end(); ++k) {
      const size_t b = begin[k], e = begin[k + 1];
      if (b == e) continue;
      double sum_w[records::kModalityCount] = {};
      double sum_wc[records::kModalityCount][records::kValueChannels] = {};
      double sum_wcc[records::kModalityCount][records::kValueChannels] = {};
      double best_w[records::kModalityCount] = {};
      size_t best_i[records::kModalityCount] = {};
      for (size_t i = b; i < e; ++i) {
        const double w = weight[i];
        if (!(w > 0.0)) continue;
        const int c = int(FusedChannelOf(Modality(recs.modality[i])));
        double v[records::kValueChannels];
        values->Read(i, v);
        sum_w[c] += w;
        for (int ch = 0; ch < records::kValueChannels; ++ch) {
          const double x = v[ch];
          sum_wc[c][ch] += w * x;
          sum_wcc[c][ch] += w * x * x;
        }
        if (w > best_w[c]) {
          best_w[c] = w;
          best_i[c] = i;
        }
      }
      for (int c = 1; c < records::kModalityCount; ++c) {
        if (!(sum_w[c] > 0.0)) continue;
        records::FusedModality& f = *channel[c];
        double variance = 0.0;
        double nearest[records::kValueChannels];
        if (profile.mode == FusionMode::kNearest) values->Read(best_i[c], nearest);
        for (int ch = 0; ch < f.channels; ++ch) {
          const double mean = sum_wc[c][ch] / sum_w[c];
          variance += std::max(0.0, sum_wcc[c][ch] / sum_w[c] - mean * mean);
          f.value[k * f.channels + ch] =
              float(profile.mode == FusionMode::kNearest ? nearest[ch] : mean);
        }
        variance /= f.channels;
        f.weight[k] = float(sum_w[c]);
        f.uncertainty[k] = float(std::sqrt(variance + 1.0 / sum_w[c]));  // spread ⊕ 1/sqrt(Σw)
      }
    }
  });
  return out;
}

}  // namespace vasl::fusion

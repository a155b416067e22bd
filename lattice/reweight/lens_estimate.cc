#include "lattice/reweight/lens_estimate.h"

#include <algorithm>
#include <cmath>
#include <optional>
#include <tuple>

#include <tbb/blocked_range.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_sort.h>

#include "absl/strings/str_cat.h"
#include "lattice/fusion/fuse.h"

namespace vasl::reweight {

using records::Modality;

namespace {

constexpr int kC = records::kValueChannels;
constexpr double kRobustCut = 3.5;   // samples beyond this many robust deviations are dropped
constexpr double kSignificance = 3;  // standard errors a finding must clear

/// A record of the camera with its leave-one-out reference.
struct Sample {
  float u, v;      // pixel
  int32_t slot;    // index into the frames
  float y[kC];     // its value, a_{m,c} applied
  float x[kC];     // the vossel's other records' weighted mean
  float w;         // its weight, shrunk when the reference has little weight
};

/// The samples of the frames under `profile`, whose record weights are `weights`; `w0` are the
/// base profile's weights, which the samples keep in every round.
std::vector<Sample> CollectSamples(const records::RecordSet& recs,
                                   const fusion::RecordWeightsResult& weights,
                                   const std::vector<float>& w0,
                                   const fusion::RecordValues& values,
                                   const std::vector<std::array<float, kC>>& base_gain,
                                   const std::vector<int32_t>& slot_of) {
  tbb::enumerable_thread_specific<std::vector<Sample>> local;
  const size_t vossels = weights.begin.size() - 1;
  tbb::parallel_for(tbb::blocked_range<size_t>(0, vossels, 2048),
                    [&](const tbb::blocked_range<size_t>& range) {
    std::vector<Sample>& out = local.local();
    for (size_t k = range.begin(); k != range.end(); ++k) {
      const size_t b = weights.begin[k], e = weights.begin[k + 1];
      double sum_w = 0.0, sum_wx[kC] = {0, 0, 0};
      bool any = false;
      for (size_t i = b; i < e; ++i) {
        const int32_t s = recs.scan[i];
        any |= s >= 0 && size_t(s) < slot_of.size() && slot_of[size_t(s)] >= 0;
      }
      if (!any) continue;
      for (size_t i = b; i < e; ++i) {
        const double w = weights.weight[i];
        if (!(w > 0.0) || fusion::FusedChannelOf(Modality(recs.modality[i])) != Modality::kRgb) {
          continue;
        }
        double x[kC];
        values.Read(i, x);
        sum_w += w;
        for (int c = 0; c < kC; ++c) sum_wx[c] += w * x[c];
      }
      for (size_t i = b; i < e; ++i) {
        const int32_t s = recs.scan[i];
        if (s < 0 || size_t(s) >= slot_of.size() || slot_of[size_t(s)] < 0) continue;
        if (Modality(recs.modality[i]) != Modality::kRgb || !(w0[i] > 0.0f)) continue;
        const double w = weights.weight[i] > 0.0f ? double(weights.weight[i]) : 0.0;
        double x[kC];
        values.Read(i, x);
        const double rest = sum_w - w;
        if (!(rest > 1e-6 * std::max(1.0, sum_w))) continue;  // no other record
        Sample smp;
        smp.u = recs.uv_px[2 * i];
        smp.v = recs.uv_px[2 * i + 1];
        smp.slot = slot_of[size_t(s)];
        for (int c = 0; c < kC; ++c) {
          smp.y[c] = base_gain[size_t(s)][c] * recs.value[i * kC + c];
          smp.x[c] = float((sum_wx[c] - w * x[c]) / rest);
        }
        smp.w = float(double(w0[i]) * rest / (rest + double(w0[i])));
        out.push_back(smp);
      }
    }
  });
  // One array, each thread's part freed as it is taken (at most one part held twice).
  size_t total = 0;
  for (const std::vector<Sample>& v : local) total += v.size();
  std::vector<Sample> all;
  all.reserve(total);
  for (std::vector<Sample>& v : local) {
    all.insert(all.end(), v.begin(), v.end());
    std::vector<Sample>().swap(v);
  }
  return all;
}

/// The grid cell of a sample.
struct CellOf {
  int grid_w, grid_h, W, H;
  CellOf(const fusion::LensMap& map, int width_px, int height_px)
      : grid_w(map.grid_w), grid_h(map.grid_h), W(width_px), H(height_px) {}
  size_t operator()(const Sample& s) const {
    const int cx = std::clamp(int(s.u * grid_w / W), 0, grid_w - 1);
    const int cy = std::clamp(int(s.v * grid_h / H), 0, grid_h - 1);
    return size_t(cy) * size_t(grid_w) + size_t(cx);
  }
};

/// Sorts `samples` into a fixed order, whatever the threads did: by cell, then pixel, then
/// frame; returns each cell's first sample (cells + 1 offsets), so a cell's samples lie
/// contiguous for its fit.
std::vector<size_t> SortByCell(std::vector<Sample>& samples, const CellOf& cell_of) {
  tbb::parallel_sort(samples.begin(), samples.end(), [&](const Sample& a, const Sample& b) {
    const size_t ca = cell_of(a), cb = cell_of(b);
    return std::tie(ca, a.v, a.u, a.slot, a.y[0], a.x[0]) <
           std::tie(cb, b.v, b.u, b.slot, b.y[0], b.x[0]);
  });
  std::vector<size_t> first(size_t(cell_of.grid_w) * size_t(cell_of.grid_h) + 1, 0);
  for (const Sample& s : samples) ++first[cell_of(s) + 1];
  for (size_t c = 1; c < first.size(); ++c) first[c] += first[c - 1];
  return first;
}

/// g_m per frame and channel: the median of y / (D·x + v) under `map`.
std::vector<std::array<float, kC>> FrameGains(const std::vector<Sample>& samples, size_t frames,
                                              const fusion::LensMap& map) {
  std::vector<std::array<std::vector<float>, kC>> ratio(frames);
  for (const Sample& s : samples) {
    float d[kC], v[kC];
    map.Sample(s.u, s.v, d, v);
    for (int c = 0; c < kC; ++c) {
      const float model = d[c] * s.x[c] + v[c];
      if (model > 0.02f && s.y[c] > 0.0f) ratio[size_t(s.slot)][c].push_back(s.y[c] / model);
    }
  }
  std::vector<std::array<float, kC>> gain(frames);
  for (size_t f = 0; f < frames; ++f) {
    for (int c = 0; c < kC; ++c) {
      std::vector<float>& r = ratio[f][c];
      if (r.empty()) {
        gain[f][c] = 1.0f;
        continue;
      }
      std::nth_element(r.begin(), r.begin() + r.size() / 2, r.end());
      gain[f][c] = r[r.size() / 2];
    }
  }
  return gain;
}

/// Weighted sums of one cell and channel over the samples kept.
struct Sums {
  double w = 0, w2 = 0, x = 0, xx = 0, t = 0, xt = 0;
};

/// D and v of one cell, per channel (see the header): the robust fit and the decision are
/// made on the channels' sum (so that noise in one channel does not make dirt of its own);
/// each channel then fits the model chosen.
void FitCell(const Sample* cell, size_t n, const std::vector<std::array<float, kC>>& gain,
             const LensOptions& o, float* d_out, float* v_out) {
  std::fill(d_out, d_out + kC, 1.0f);
  std::fill(v_out, v_out + kC, 0.0f);
  std::vector<double> t(n * (kC + 1)), x(n * (kC + 1));  // channels, then their sum
  for (size_t i = 0; i < n; ++i) {
    double* ti = &t[i * (kC + 1)];
    double* xi = &x[i * (kC + 1)];
    ti[kC] = xi[kC] = 0.0;
    for (int c = 0; c < kC; ++c) {
      ti[c] = double(cell[i].y[c]) / std::max(1e-6f, gain[size_t(cell[i].slot)][c]);
      xi[c] = cell[i].x[c];
      ti[kC] += ti[c];
      xi[kC] += xi[c];
    }
  }
  std::vector<char> keep(n, 1);
  auto sums = [&](int c) {
    Sums s;
    for (size_t i = 0; i < n; ++i) {
      if (!keep[i]) continue;
      const double w = cell[i].w, xc = x[i * (kC + 1) + c], tc = t[i * (kC + 1) + c];
      s.w += w;
      s.w2 += w * w;
      s.x += w * xc;
      s.xx += w * xc * xc;
      s.t += w * tc;
      s.xt += w * xc * tc;
    }
    return s;
  };
  auto residual = [&](size_t i, int c, double d, double v) {
    return t[i * (kC + 1) + c] - d * x[i * (kC + 1) + c] - v;
  };
  auto sigma2 = [&](int c, double d, double v, const Sums& s) {
    double r2 = 0.0;
    for (size_t i = 0; i < n; ++i) {
      if (keep[i]) r2 += cell[i].w * residual(i, c, d, v) * residual(i, c, d, v);
    }
    return r2 / std::max(1e-30, s.w);
  };
  auto determined = [](const Sums& s) { return s.w * s.xx - s.x * s.x > 1e-9 * s.w * s.xx; };
  auto full_fit = [&](const Sums& s, double* d, double* v) {
    if (!determined(s)) {
      *d = s.xx > 0.0 ? s.xt / s.xx : 1.0;
      *v = 0.0;
      return;
    }
    *d = (s.w * s.xt - s.x * s.t) / (s.w * s.xx - s.x * s.x);
    *v = (s.t - *d * s.x) / s.w;
  };
  // The sum of the channels: robust fit, then the decision.
  double d = 1.0, v = 0.0;
  for (int pass = 0; pass < 2; ++pass) {
    const Sums s = sums(kC);
    if (!(s.w > 0.0)) return;
    full_fit(s, &d, &v);
    std::vector<double> r;
    for (size_t i = 0; i < n; ++i) {
      if (keep[i]) r.push_back(std::abs(residual(i, kC, d, v)));
    }
    std::nth_element(r.begin(), r.begin() + r.size() / 2, r.end());
    const double cut = kRobustCut * std::max(1e-4, 1.4826 * r[r.size() / 2]);
    for (size_t i = 0; i < n; ++i) {
      if (keep[i] && std::abs(residual(i, kC, d, v)) > cut) keep[i] = 0;
    }
  }
  if (int64_t(std::count(keep.begin(), keep.end(), 1)) < o.min_samples) return;
  const Sums s = sums(kC);
  if (!(s.xx > 0.0)) return;
  const double scale = s.w2 / s.w;  // weights are relative, not inverse variances: Σw/n_eff
  const double min_veil = kC * o.min_veil;  // the sum of three channels' veil
  // Each alone: dirt t = D·x, veil t = x + v. Either moves the cell's mean; a loss of contrast
  // that keeps the mean (blur, a footprint the other frames see otherwise) is neither.
  const double d1 = s.xt / s.xx;
  const double v1 = (s.t - s.x) / s.w;
  const double r_d = sigma2(kC, d1, 0.0, s), r_v = sigma2(kC, 1.0, v1, s);
  const bool dirt1 =
      1.0 - d1 > o.min_dirt && 1.0 - d1 > kSignificance * std::sqrt(r_d / s.xx * scale);
  const bool veil1 = v1 > min_veil && v1 > kSignificance * std::sqrt(r_v / s.w * scale);
  if (!dirt1 && !veil1) return;
  // Both at once, when one alone was found and the other clears its bounds beside it.
  bool dirt = dirt1 && (!veil1 || r_d <= r_v), veil = veil1 && !dirt;
  if (determined(s)) {
    full_fit(s, &d, &v);
    const double det = s.w * s.xx - s.x * s.x;
    const double s2 = sigma2(kC, d, v, s);
    if (1.0 - d > o.min_dirt && 1.0 - d > kSignificance * std::sqrt(s2 * s.w / det * scale) &&
        v > min_veil && v > kSignificance * std::sqrt(s2 * s.xx / det * scale)) {
      dirt = veil = true;
    }
  }
  if (!dirt && !veil) return;
  for (int c = 0; c < kC; ++c) {  // each channel under the model found
    const Sums sc = sums(c);
    double dc = 1.0, vc = 0.0;
    if (dirt && veil) full_fit(sc, &dc, &vc);
    else if (dirt) dc = sc.xx > 0.0 ? sc.xt / sc.xx : 1.0;
    else vc = (sc.t - sc.x) / sc.w;
    d_out[c] = float(std::clamp(dc, 0.05, 1.0));
    v_out[c] = float(std::max(0.0, vc));
  }
}

/// RMS of log y − log(g·(D·x + v)) over the samples where both are positive.
double LogResidual(const std::vector<Sample>& samples, const fusion::LensMap& map,
                   const std::vector<std::array<float, kC>>& gain) {
  double sum = 0.0, n = 0.0;
  for (const Sample& s : samples) {
    float d[kC], v[kC];
    map.Sample(s.u, s.v, d, v);
    for (int c = 0; c < kC; ++c) {
      const double model = gain[size_t(s.slot)][c] * (d[c] * s.x[c] + v[c]);
      if (model > 0.01 && s.y[c] > 0.01f) {
        const double r = std::log(double(s.y[c]) / model);
        sum += s.w * r * r;
        n += s.w;
      }
    }
  }
  return n > 0.0 ? std::sqrt(sum / n) : 0.0;
}

}  // namespace

absl::StatusOr<LensEstimate> EstimateLensMap(const records::RecordSet& recs, size_t vossel_count,
                                             double vossel_size_m,
                                             const fusion::WeightingProfile& base,
                                             const std::vector<LensFrame>& frames,
                                             const LensOptions& o) {
  if (frames.size() < 2) {
    return absl::FailedPreconditionError(absl::StrCat(
        "a lens map is found from a sequence of frames of one camera; got ", frames.size()));
  }
  if (o.cell_px < 0 || o.samples_per_cell < 1 || o.min_samples < 3 || o.rounds < 1 ||
      !(o.min_dirt >= 0.0 && o.min_dirt < 1.0) || !(o.min_veil >= 0.0)) {
    return absl::InvalidArgumentError("lens estimate options out of range");
  }
  const int W = frames[0].width_px, H = frames[0].height_px;
  int32_t max_source = 0;
  for (const LensFrame& f : frames) {
    if (f.width_px != W || f.height_px != H || W <= 0 || H <= 0) {
      return absl::InvalidArgumentError(absl::StrCat(
          "the frames of one lens map must share their image size; source ", f.source, " is ",
          f.width_px, "x", f.height_px, ", source ", frames[0].source, " ", W, "x", H));
    }
    if (base.lens != nullptr && base.lens->by_source.count(f.source)) {
      return absl::InvalidArgumentError(absl::StrCat(
          "the base profile applies a lens map to source ", f.source, " already"));
    }
    max_source = std::max(max_source, f.source);
  }
  for (int32_t s : recs.scan) max_source = std::max(max_source, s);
  std::vector<int32_t> slot_of(size_t(max_source) + 1, -1);
  for (size_t i = 0; i < frames.size(); ++i) slot_of[size_t(frames[i].source)] = int32_t(i);

  absl::StatusOr<fusion::RecordWeightsResult> w0 =
      fusion::RecordWeights(recs, vossel_count, vossel_size_m, base);
  if (!w0.ok()) return w0.status();
  std::vector<std::array<float, kC>> base_gain = fusion::DenseChannelGains(base, recs);
  if (base_gain.size() < slot_of.size()) base_gain.resize(slot_of.size(), {1.0f, 1.0f, 1.0f});

  LensEstimate out;
  fusion::LensMap& map = out.map;
  map.image_w = W;
  map.image_h = H;
  std::vector<std::array<float, kC>> gain(frames.size(), {1.0f, 1.0f, 1.0f});
  // g_m as the map keeps it: on the raw record values, which fusion scales by a_{m,c} after.
  auto set_source_gains = [&](fusion::LensMap& m) {
    for (size_t f = 0; f < frames.size(); ++f) {
      std::array<float, kC> g{};
      for (int c = 0; c < kC; ++c) g[c] = gain[f][c] / base_gain[size_t(frames[f].source)][c];
      m.source_gain[frames[f].source] = g;
    }
  };
  for (int round = 0; round < o.rounds; ++round) {
    // References under the map found so far (none in the first round).
    fusion::WeightingProfile profile = base;
    std::optional<fusion::RecordWeightsResult> weights_r;
    if (round > 0) {
      auto current = std::make_shared<fusion::LensMap>(map);
      set_source_gains(*current);
      std::vector<std::shared_ptr<const fusion::LensMap>> maps;
      if (base.lens != nullptr) maps = base.lens->maps;
      maps.push_back(current);
      profile.lens = fusion::LensTable::Of(std::move(maps));
      absl::StatusOr<fusion::RecordWeightsResult> w =
          fusion::RecordWeights(recs, vossel_count, vossel_size_m, profile);
      if (!w.ok()) return w.status();
      weights_r = std::move(*w);
    }
    absl::StatusOr<fusion::RecordValues> values = fusion::RecordValues::Of(profile, recs);
    if (!values.ok()) return values.status();
    std::vector<Sample> samples = CollectSamples(
        recs, round > 0 ? *weights_r : *w0, w0->weight, *values, base_gain, slot_of);
    if (samples.empty()) {
      return absl::FailedPreconditionError(
          "no record of the camera's frames shares a vossel with another record: nothing to "
          "compare its pixels with");
    }
    if (round == 0) {
      out.samples = int64_t(samples.size());
      double cell = o.cell_px;
      if (cell <= 0.0) {
        const double cells = std::max(1.0, double(samples.size()) / o.samples_per_cell);
        cell = std::sqrt(double(W) * H / cells);
      }
      cell = std::clamp(cell, std::max(2.0, W / 1024.0), std::max(2.0, W / 8.0));
      map.grid_w = std::max(1, int(std::ceil(W / cell)));
      map.grid_h = std::max(1, int(std::ceil(H / cell)));
      out.cell_px = double(W) / map.grid_w;
      out.cells = int64_t(map.grid_w) * map.grid_h;
      map.transmission.assign(size_t(out.cells) * kC, 1.0f);
      map.veil.assign(size_t(out.cells) * kC, 0.0f);
    }
    const std::vector<size_t> first = SortByCell(samples, CellOf(map, W, H));
    if (round == 0) out.residual_before = LogResidual(samples, map, gain);
    gain = FrameGains(samples, frames.size(), map);
    auto cell_size = [&](size_t cell) { return first[cell + 1] - first[cell]; };
    std::vector<float> d_next(map.transmission.size(), 1.0f), v_next(map.veil.size(), 0.0f);
    tbb::parallel_for(tbb::blocked_range<size_t>(0, size_t(out.cells), 16),
                      [&](const tbb::blocked_range<size_t>& r) {
      for (size_t cell = r.begin(); cell != r.end(); ++cell) {
        if (int64_t(cell_size(cell)) < o.min_samples) continue;
        FitCell(&samples[first[cell]], cell_size(cell), gain, o, &d_next[cell * kC],
                &v_next[cell * kC]);
      }
    });
    map.transmission = std::move(d_next);
    map.veil = std::move(v_next);
    if (round + 1 == o.rounds) {
      out.residual_after = LogResidual(samples, map, gain);
      out.cells_fitted = 0;
      for (size_t cell = 0; cell < size_t(out.cells); ++cell) {
        out.cells_fitted += int64_t(cell_size(cell)) >= o.min_samples;
      }
    }
  }
  set_source_gains(map);
  for (size_t cell = 0; cell < size_t(out.cells); ++cell) {
    bool dirt = false, veil = false;
    for (int c = 0; c < kC; ++c) {
      dirt |= map.transmission[cell * kC + c] < 1.0f;
      veil |= map.veil[cell * kC + c] > 0.0f;
    }
    out.cells_dirt += dirt;
    out.cells_veil += veil;
  }
  return out;
}

}  // namespace vasl::reweight

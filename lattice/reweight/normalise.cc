#include "lattice/reweight/normalise.h"

#include <algorithm>
#include <cmath>
#include <numeric>
#include <set>
#include <utility>

#include <Eigen/Core>
#include <Eigen/Sparse>
#include <tbb/blocked_range.h>
#include <tbb/parallel_reduce.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

namespace vasl::reweight {

using records::kValueChannels;
using records::Modality;

namespace {

/// Vossels per leaf task of the deterministic reductions.
constexpr size_t kVosselGrain = 2048;
/// A pivot of the factorised block below this fraction of its largest diagonal entry means the
/// gains are not determined by the data.
constexpr double kPivotTolerance = 1e-12;

using Gains = std::array<double, kValueChannels>;
using PairKey = std::pair<int32_t, int32_t>;  // (m, n), m < n

/// One source's merged observation of one vossel: weight Σw and Σ w·C per channel.
struct Observation {
  int32_t source = 0;
  double w = 0.0;
  Gains wc{};
};

/// The observations of vossel k that take part (modality, not derived, weight > 0), one per
/// source, ascending by source id. Counts records taking part with a bad weight or value.
void GatherVossel(const records::RecordSet& recs, const std::vector<size_t>& begin,
                  const std::vector<float>& weight, Modality modality, int channels, size_t k,
                  std::vector<Observation>& out, int64_t& bad_weights, int64_t& bad_values) {
  out.clear();
  for (size_t i = begin[k]; i < begin[k + 1]; ++i) {
    if (Modality(recs.modality[i]) != modality) continue;
    if (recs.flags[i] & records::kFlagDerived) continue;
    const float w = weight[i];
    if (!std::isfinite(w) || w < 0.0f) {
      ++bad_weights;
      continue;
    }
    if (w == 0.0f) continue;
    const float* v = &recs.value[i * kValueChannels];
    bool finite = true;
    for (int c = 0; c < channels; ++c) finite = finite && std::isfinite(v[c]);
    if (!finite) {
      ++bad_values;
      continue;
    }
    const int32_t s = recs.scan[i];
    auto it = std::find_if(out.begin(), out.end(),
                           [s](const Observation& o) { return o.source == s; });
    if (it == out.end()) {
      out.push_back({s, 0.0, {}});
      it = out.end() - 1;
    }
    it->w += w;
    for (int c = 0; c < channels; ++c) it->wc[c] += double(w) * double(v[c]);
  }
  std::sort(out.begin(), out.end(),
            [](const Observation& a, const Observation& b) { return a.source < b.source; });
}

/// Normal-equation sums of one pair of sources over the vossels they share:
/// Σ p C_m², Σ p C_n², Σ p C_m C_n per channel with p = w_m w_n.
struct PairSums {
  int64_t shared = 0;
  Gains smm{}, snn{}, smn{};
};

/// Pass 1: pair sums, the sources taking part and the bad-input counts.
struct Accumulation {
  std::map<PairKey, PairSums> pairs;
  std::set<int32_t> sources;
  int64_t bad_weights = 0;
  int64_t bad_values = 0;

  void Join(const Accumulation& o) {
    for (const auto& [key, b] : o.pairs) {
      PairSums& a = pairs[key];
      a.shared += b.shared;
      for (int c = 0; c < kValueChannels; ++c) {
        a.smm[c] += b.smm[c];
        a.snn[c] += b.snn[c];
        a.smn[c] += b.smn[c];
      }
    }
    sources.insert(o.sources.begin(), o.sources.end());
    bad_weights += o.bad_weights;
    bad_values += o.bad_values;
  }
};

/// Pass 2: the objective at a = 1 and at the solution over the terms of linked pairs.
struct CostSums {
  int64_t vossels_used = 0;
  int64_t pairs_used = 0;
  double sum_p = 0.0;
  Gains before{}, after{};

  void Join(const CostSums& o) {
    vossels_used += o.vossels_used;
    pairs_used += o.pairs_used;
    sum_p += o.sum_p;
    for (int c = 0; c < kValueChannels; ++c) {
      before[c] += o.before[c];
      after[c] += o.after[c];
    }
  }
};

absl::Status ValidateInputs(const records::RecordSet& recs, const std::vector<size_t>& begin,
                            const std::vector<float>& weight, const NormaliseOptions& options) {
  const size_t n = recs.size();
  if (recs.scan.size() != n || recs.modality.size() != n || recs.flags.size() != n ||
      recs.value.size() != n * kValueChannels) {
    return absl::InvalidArgumentError(
        "normalisation: the record set's arrays (vossel, scan, modality, flags, value) differ "
        "in length");
  }
  if (weight.size() != n) {
    return absl::InvalidArgumentError(absl::StrCat(
        "normalisation: ", weight.size(), " weights for ", n,
        " records; pass the weights fusion::RecordWeights returned for these records"));
  }
  if (begin.empty() || begin.front() != 0 || begin.back() != n) {
    return absl::InvalidArgumentError(absl::StrCat(
        "normalisation: vossel offsets must run from 0 to the record count ", n, " (got ",
        begin.size(), " offsets", begin.empty() ? "" : absl::StrCat(", last ", begin.back()),
        "); pass the offsets fusion::RecordWeights returned for these records"));
  }
  if (!std::is_sorted(begin.begin(), begin.end())) {
    return absl::InvalidArgumentError("normalisation: vossel offsets are not ascending");
  }
  switch (options.modality) {
    case Modality::kLidar:
    case Modality::kRgb:
    case Modality::kIr:
    case Modality::kRadar:
      break;
    default:
      return absl::InvalidArgumentError(absl::StrCat(
          "normalisation: modality ", records::ModalityName(options.modality),
          " cannot be normalised; use a captured modality (RGB, LiDAR, IR, radar)"));
  }
  if (options.min_shared_vossels < 1) {
    return absl::InvalidArgumentError("normalisation: min_shared_vossels must be at least 1");
  }
  return absl::OkStatus();
}

/// A component's linked pairs: ((m, n) in the component's local indices, their sums).
using LocalPairs = std::vector<std::pair<std::pair<int, int>, const PairSums*>>;

/// Minimises aᵀQa subject to Σa = N for one component and channel (the header's 2 × 2
/// reduction), N = n, writing a. `ref` is the local index of the source taken apart. Returns
/// false when the factorised block is singular (the data do not determine the gains).
bool SolveComponentChannel(int n, int ref, const LocalPairs& pairs, int c,
                           std::vector<double>& a) {
  const auto other = [ref](int i) { return i < ref ? i : i - 1; };
  const int no = n - 1;
  std::vector<Eigen::Triplet<double>> triplets;
  triplets.reserve(pairs.size() * 4);
  Eigen::VectorXd q_or = Eigen::VectorXd::Zero(no);
  double q_rr = 0.0;
  for (const auto& [mn, sums] : pairs) {
    const auto [m, nn] = mn;
    const double dm = sums->smm[c], dn = sums->snn[c], off = -sums->smn[c];
    if (m == ref) {
      q_rr += dm;
    } else {
      triplets.emplace_back(other(m), other(m), dm);
    }
    if (nn == ref) {
      q_rr += dn;
    } else {
      triplets.emplace_back(other(nn), other(nn), dn);
    }
    if (m == ref) {
      q_or[other(nn)] += off;
    } else if (nn == ref) {
      q_or[other(m)] += off;
    } else {
      triplets.emplace_back(other(m), other(nn), off);
      triplets.emplace_back(other(nn), other(m), off);
    }
  }
  Eigen::SparseMatrix<double> q_oo(no, no);
  q_oo.setFromTriplets(triplets.begin(), triplets.end());  // sums duplicates
  const double d_max = q_oo.diagonal().maxCoeff();
  if (!(d_max > 0.0) || !(q_rr > 0.0)) return false;
  Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> ldlt(q_oo);
  if (ldlt.info() != Eigen::Success) return false;
  if (!(ldlt.vectorD().minCoeff() > kPivotTolerance * d_max)) return false;
  const Eigen::VectorXd x = ldlt.solve(Eigen::VectorXd::Ones(no));
  const Eigen::VectorXd y = ldlt.solve(q_or);
  const double s = q_rr - q_or.dot(y);  // Schur complement of Q_oo, ≥ 0
  const double t = 1.0 - y.sum();
  const double det = s * x.sum() + t * t;
  if (!(det > 0.0)) return false;
  const double a_r = double(n) * t / det;
  const double mu = double(n) * s / det;
  a.assign(size_t(n), 0.0);
  for (int i = 0; i < n; ++i) a[size_t(i)] = i == ref ? a_r : mu * x[other(i)] - a_r * y[other(i)];
  // Σa = N holds in exact arithmetic; remove the rounding so the mean is 1 to the last bits.
  const double sum = std::accumulate(a.begin(), a.end(), 0.0);
  for (double& g : a) g *= double(n) / sum;
  return true;
}

int FindRoot(std::vector<int>& parent, int i) {
  while (parent[size_t(i)] != i) {
    parent[size_t(i)] = parent[size_t(parent[size_t(i)])];
    i = parent[size_t(i)];
  }
  return i;
}

}  // namespace

absl::StatusOr<NormaliseResult> SolveChannelGains(const records::RecordSet& recs,
                                                  const std::vector<size_t>& begin,
                                                  const std::vector<float>& weight,
                                                  const NormaliseOptions& options) {
  if (absl::Status s = ValidateInputs(recs, begin, weight, options); !s.ok()) return s;
  const Modality modality = options.modality;
  const int channels = records::ChannelCount(modality);
  const size_t vossel_count = begin.size() - 1;

  // Pass 1: the normal equations, per (m, n) pair of sources, reduced in a fixed order.
  const Accumulation acc = tbb::parallel_deterministic_reduce(
      tbb::blocked_range<size_t>(0, vossel_count, kVosselGrain), Accumulation{},
      [&](const tbb::blocked_range<size_t>& range, Accumulation body) {
        std::vector<Observation> obs;
        for (size_t k = range.begin(); k != range.end(); ++k) {
          GatherVossel(recs, begin, weight, modality, channels, k, obs, body.bad_weights,
                       body.bad_values);
          for (const Observation& o : obs) body.sources.insert(o.source);
          for (size_t i = 0; i < obs.size(); ++i) {
            for (size_t j = i + 1; j < obs.size(); ++j) {
              const double p = obs[i].w * obs[j].w;
              PairSums& sums = body.pairs[{obs[i].source, obs[j].source}];
              ++sums.shared;
              for (int c = 0; c < channels; ++c) {
                const double cm = obs[i].wc[c] / obs[i].w, cn = obs[j].wc[c] / obs[j].w;
                sums.smm[c] += p * cm * cm;
                sums.snn[c] += p * cn * cn;
                sums.smn[c] += p * cm * cn;
              }
            }
          }
        }
        return body;
      },
      [](Accumulation a, const Accumulation& b) {
        a.Join(b);
        return a;
      });
  if (acc.bad_weights > 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        "normalisation: ", acc.bad_weights, " records have a negative or non-finite weight"));
  }
  if (acc.bad_values > 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        "normalisation: ", acc.bad_values, " records with weight > 0 have non-finite values"));
  }

  // Sources in dense indices, linked pairs, connected components (union-find).
  const std::vector<int32_t> sources(acc.sources.begin(), acc.sources.end());
  const auto index_of = [&sources](int32_t s) {
    return int(std::lower_bound(sources.begin(), sources.end(), s) - sources.begin());
  };
  std::vector<std::pair<PairKey, const PairSums*>> linked;
  for (const auto& [key, sums] : acc.pairs) {
    if (sums.shared >= options.min_shared_vossels) linked.emplace_back(key, &sums);
  }
  if (linked.empty()) {
    return absl::FailedPreconditionError(absl::StrCat(
        "normalisation needs two sources sharing at least ", options.min_shared_vossels,
        " vossels with ", records::ModalityName(modality), " records of weight > 0; ",
        sources.size(), " source(s) take part and no pair shares that many"));
  }
  std::vector<int> parent(sources.size());
  std::iota(parent.begin(), parent.end(), 0);
  std::vector<int64_t> degree(sources.size(), 0);  // shared vossels over linked pairs
  for (const auto& [key, sums] : linked) {
    const int m = index_of(key.first), n = index_of(key.second);
    degree[size_t(m)] += sums->shared;
    degree[size_t(n)] += sums->shared;
    const int rm = FindRoot(parent, m), rn = FindRoot(parent, n);
    if (rm != rn) parent[size_t(std::max(rm, rn))] = std::min(rm, rn);
  }

  NormaliseResult result;
  std::map<int, std::vector<int>> members;  // root → dense indices, ascending
  for (int i = 0; i < int(sources.size()); ++i) {
    if (degree[size_t(i)] == 0) {
      result.unlinked_sources.push_back(sources[size_t(i)]);
      result.gain[sources[size_t(i)]] = {1.0, 1.0, 1.0};
    } else {
      members[FindRoot(parent, i)].push_back(i);
    }
  }

  // One sparse solve per component and channel.
  std::vector<Gains> gain_dense(sources.size(), Gains{1.0, 1.0, 1.0});
  for (const auto& [root, comp] : members) {
    const int n = int(comp.size());
    std::vector<int> local(sources.size(), -1);
    for (int i = 0; i < n; ++i) local[size_t(comp[size_t(i)])] = i;
    LocalPairs pairs;
    for (const auto& [key, sums] : linked) {
      const int m = local[size_t(index_of(key.first))];
      if (m >= 0) pairs.push_back({{m, local[size_t(index_of(key.second))]}, sums});
    }
    int ref = 0;  // the best-connected source is taken apart
    for (int i = 1; i < n; ++i) {
      if (degree[size_t(comp[size_t(i)])] > degree[size_t(comp[size_t(ref)])]) ref = i;
    }
    std::vector<int32_t> ids;
    for (int i : comp) ids.push_back(sources[size_t(i)]);
    std::vector<double> a;
    for (int c = 0; c < channels; ++c) {
      const bool ok = SolveComponentChannel(n, ref, pairs, c, a) &&
                      std::all_of(a.begin(), a.end(),
                                  [](double g) { return std::isfinite(g) && g > 0.0; });
      if (!ok) {
        return absl::FailedPreconditionError(absl::StrCat(
            "normalisation: the data do not determine positive gains of channel ", c,
            " for sources {", absl::StrJoin(ids, ", "),
            "}: their values on the shared vossels vanish or differ in sign"));
      }
      for (int i = 0; i < n; ++i) gain_dense[size_t(comp[size_t(i)])][size_t(c)] = a[size_t(i)];
    }
    for (int i : comp) result.gain[sources[size_t(i)]] = gain_dense[size_t(i)];
    result.components.push_back(std::move(ids));
  }

  // Pass 2: the objective before and after over the terms used, exactly as defined.
  std::set<PairKey> linked_keys;
  for (const auto& [key, sums] : linked) linked_keys.insert(key);
  const CostSums cost = tbb::parallel_deterministic_reduce(
      tbb::blocked_range<size_t>(0, vossel_count, kVosselGrain), CostSums{},
      [&](const tbb::blocked_range<size_t>& range, CostSums body) {
        std::vector<Observation> obs;
        int64_t bad_w = 0, bad_v = 0;
        for (size_t k = range.begin(); k != range.end(); ++k) {
          GatherVossel(recs, begin, weight, modality, channels, k, obs, bad_w, bad_v);
          bool used = false;
          for (size_t i = 0; i < obs.size(); ++i) {
            for (size_t j = i + 1; j < obs.size(); ++j) {
              if (!linked_keys.count({obs[i].source, obs[j].source})) continue;
              used = true;
              ++body.pairs_used;
              const double p = obs[i].w * obs[j].w;
              body.sum_p += p;
              const Gains& am = gain_dense[size_t(index_of(obs[i].source))];
              const Gains& an = gain_dense[size_t(index_of(obs[j].source))];
              for (int c = 0; c < channels; ++c) {
                const double cm = obs[i].wc[c] / obs[i].w, cn = obs[j].wc[c] / obs[j].w;
                body.before[c] += p * (cm - cn) * (cm - cn);
                const double d = am[c] * cm - an[c] * cn;
                body.after[c] += p * d * d;
              }
            }
          }
          body.vossels_used += used ? 1 : 0;
        }
        return body;
      },
      [](CostSums a, const CostSums& b) {
        a.Join(b);
        return a;
      });
  result.vossels_used = cost.vossels_used;
  result.pairs_used = cost.pairs_used;
  for (int c = 0; c < channels; ++c) {
    result.cost_before[c] = cost.before[c] / cost.sum_p;
    result.cost_after[c] = cost.after[c] / cost.sum_p;
  }
  return result;
}

}  // namespace vasl::reweight

/// @file normalise.h
/// @brief Multi-scan radiometric normalisation (VASL-MODEL §7): per-source per-channel gains
///        a_{m,c} that make overlapping sources agree, solved as a sparse least-squares problem.
/// @details For every channel c the gains minimise
///          ```
///          E_c(a) = Σ_k Σ_{m<n} w_{k,m} w_{k,n} (a_{m,c} C_{k,m,c} − a_{n,c} C_{k,n,c})²
///          ```
///          subject to a mean gain of 1. E_c(a) = aᵀ Q a with Q sparse, symmetric and positive
///          semi-definite (one row per source, non-zeros only between sources that share
///          vossels). The Lagrange condition of min aᵀQa s.t. Σa = N is Q a = μ·1, Σa = N. It is
///          solved exactly, with no regularisation: one source r of the component is taken apart,
///          the remaining principal block Q_oo (positive definite whenever the component is
///          connected and its values do not vanish) is factorised once with Eigen's
///          SimplicialLDLT, two solves give x = Q_oo⁻¹·1 and y = Q_oo⁻¹·Q_or, and the Lagrange
///          condition reduces to a 2 × 2 system in (a_r, μ):
///          ```
///          s = Q_rr − Q_roᵀ y,  t = 1 − Σy,  D = s·Σx + t²
///          a_r = N t / D,  μ = N s / D,  a_o = μ x − a_r y
///          ```
///          This holds also when Q is singular (noise-free data, where Q a = 0 has the exact
///          answer and μ = 0).
///
///          **Which records take part.** Records of `NormaliseOptions::modality` exactly (for kRgb:
///          raw RGB records; derived records are edits, not captures, and never take part; nor do
///          records flagged kFlagDerived), with weight > 0. Several records of one (vossel,
///          source) are merged into one observation: value Σ w C / Σ w, weight Σ w (the share
///          they have in the §7 fused value).
///
///          **Linking and disconnected sources (choice).** Two sources are *linked* when they
///          share at least `min_shared_vossels` vossels where both take part; the terms of pairs
///          that are not linked are left out of E. The "linked" graph is split into connected
///          components and each component is solved on its own with a mean gain of 1 over its
///          own sources: gains of different components are not comparable (nothing in the data
///          relates them), and a per-component mean of 1 leaves each component's overall
///          brightness as captured. Sources linked to no other source are listed in
///          `unlinked_sources` and get gain 1 on every channel. For modalities with one channel
///          (LiDAR, IR, radar) only channel 0 is solved; channels 1 and 2 report gain 1 and
///          cost 0.
///
///          **Using the gains.** They apply to raw record values, like
///          fusion::WeightingProfile::channel_gain (C_{k,m,c} fuses as a_{m,c}·C_{k,m,c}): copy
///          `gain` into a profile's channel_gain to replace, not compose with, earlier gains.
///          The weights are those of the profile being normalised, so call this with the output
///          of fusion::RecordWeights under that profile.
///
///          Cost: two parallel passes over the records (TBB; the normal equations are
///          accumulated per (m, n) pair of sources and reduced in a fixed order, so results are
///          bit-identical from run to run), then one sparse factorisation per component and
///          channel.
/// @warning Thread safety: a pure function of its arguments; concurrent calls are safe.
#pragma once

#include <array>
#include <cstdint>
#include <map>
#include <vector>

#include "absl/status/statusor.h"
#include "lattice/records/records.h"

namespace vasl::reweight {

/// Which records take part in a normalisation, and when two sources count as overlapping.
struct NormaliseOptions {
  /// The fused channel whose records take part: kRgb means raw RGB records (derived records are
  /// excluded: they are edits, not captures). kLidar, kIr and kRadar have one channel.
  /// kUnspecified and kDerived are rejected.
  records::Modality modality = records::Modality::kRgb;
  /// A pair of sources must share at least this many vossels (where both have a record with
  /// weight > 0) to link them; terms of unlinked pairs are left out. At least 1.
  int64_t min_shared_vossels = 16;
};

/// The gains and what went into them.
struct NormaliseResult {
  /// a_{m,c} per source id, for every source with a record taking part (unlinked ones: 1).
  std::map<int32_t, std::array<double, records::kValueChannels>> gain;
  /// Vossels with at least one term of a linked pair.
  int64_t vossels_used = 0;
  /// (vossel, m<n) terms of linked pairs that entered E.
  int64_t pairs_used = 0;
  /// E_c per channel at a = 1, divided by Σ w_{k,m} w_{k,n} over the terms used (a weighted
  /// mean squared difference, in squared value units).
  std::array<double, records::kValueChannels> cost_before{};
  /// E_c per channel at the solution, normalised as cost_before.
  std::array<double, records::kValueChannels> cost_after{};
  /// Sources taking part that no other source links to (gain 1), ascending.
  std::vector<int32_t> unlinked_sources;
  /// The connected components solved, each a list of source ids ascending; the mean gain over
  /// each component is 1 per channel.
  std::vector<std::vector<int32_t>> components;
};

/// Solves the §7 multi-scan normalisation gains for the records of `options.modality`.
///
/// @param records  the version's records, sorted by vossel (as fusion needs them).
/// @param begin    vossel_count + 1 offsets: vossel k's records are [begin[k], begin[k+1]),
///                 as returned by fusion::RecordWeights (RecordWeightsResult::begin).
/// @param weight   w_{k,m} per record under the profile being normalised
///                 (RecordWeightsResult::weight); records with weight 0 take no part.
/// @param options  modality and linking threshold.
/// @return the gains; INVALID_ARGUMENT when begin or weight do not match the records (sizes,
///         offsets not ascending from 0 to records.size()), a weight taking part is negative
///         or not finite, a value taking part is not finite, or the options are out of range;
///         FAILED_PRECONDITION when fewer than two sources share min_shared_vossels vossels, or
///         when a component's gains are not determined by the data in some channel (its
///         values vanish on the overlap, so the factorised block is singular).
absl::StatusOr<NormaliseResult> SolveChannelGains(const records::RecordSet& records,
                                                  const std::vector<size_t>& begin,
                                                  const std::vector<float>& weight,
                                                  const NormaliseOptions& options = {});

}  // namespace vasl::reweight

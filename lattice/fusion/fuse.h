/// @file fuse.h
/// @brief Fusion and reweighting (VASL-MODEL §7): one pass over the records.
#pragma once

#include <array>
#include <vector>

#include "absl/status/statusor.h"
#include "lattice/fusion/profile.h"
#include "lattice/records/records.h"

namespace vasl::fusion {

using records::FusedChannelOf;

/// a_{m,c} of `profile` (§7) as an array indexed by source id, covering every source id in
/// `records` (1 where the profile has none). Fusion and the §8 view blend scale C_{k,m,c} by it.
std::vector<std::array<float, records::kValueChannels>> DenseChannelGains(
    const WeightingProfile& profile, const records::RecordSet& records);

/// How fusion reads each record's value under a profile: the §9 lens map of its source, if
/// the profile applies one (AdjustForLens), then a_{m,c} (§7). Dense by source id, so that the
/// hot loops look up arrays, not maps.
class RecordValues {
 public:
  /// FAILED_PRECONDITION when the profile lists lens maps it has not resolved.
  static absl::StatusOr<RecordValues> Of(const WeightingProfile& profile,
                                         const records::RecordSet& records);
  /// Record i's value as fused, into out[kValueChannels]; returns the factors its conf[dirt]
  /// and conf[fog] take from the lens map (1 for a source without one).
  LensFactors Read(size_t i, double* out) const {
    const int32_t s = recs_->scan[i];
    const float* v = &recs_->value[i * records::kValueChannels];
    float adjusted[records::kValueChannels];
    LensFactors conf;
    if (has_lens_ && s >= 0 && lens_[size_t(s)].first != nullptr) {
      conf = AdjustThroughLens(i, adjusted);
      v = adjusted;
    }
    for (int c = 0; c < records::kValueChannels; ++c) {
      out[c] = (s >= 0 ? double(gain_[size_t(s)][c]) : 1.0) * v[c];
    }
    return conf;
  }
  /// The lens factors alone.
  LensFactors LensConfidence(size_t i) const;
  /// A colour read from source `source`'s own image at continuous pixel (uv[0], uv[1]) corrected
  /// in place as Read corrects its records' values there (§9 lens map; a_{m,c} not applied).
  void CorrectImageSample(int32_t source, const float* uv, float* value) const;
  /// Whether some source's records go through a lens map.
  bool has_lens() const { return has_lens_; }

 private:
  RecordValues(const records::RecordSet& records) : recs_(&records) {}
  /// Record i's value, whose source has a lens map, corrected by it into v[kValueChannels].
  LensFactors AdjustThroughLens(size_t i, float* v) const;
  const records::RecordSet* recs_;
  std::vector<std::array<float, records::kValueChannels>> gain_;
  /// Per source id, its lens map and g_m in it; null map: none.
  std::vector<std::pair<const LensMap*, const std::array<float, records::kValueChannels>*>> lens_;
  bool has_lens_ = false;
};

/// Offsets of each vossel's records in a RecordSet sorted by vossel: vossel k's records are
/// [begin[k], begin[k+1]). INTERNAL when the records are not sorted by a valid index.
absl::StatusOr<std::vector<size_t>> VosselOffsets(const records::RecordSet& records,
                                                  size_t vossel_count);

/// The §7 weight of every record under `profile`, with the vossel offsets it used.
struct RecordWeightsResult {
  std::vector<size_t> begin;  ///< vossel_count + 1 offsets (VosselOffsets)
  std::vector<float> weight;  ///< w_{k,m} per record; 0 for invalidated records
};

/// w_{k,m} (WeightKernel) of every record, one parallel pass; the proximity term's r_{k,min} is
/// taken per vossel and channel. Fusion and the §8 view blend both weigh records through this.
absl::StatusOr<RecordWeightsResult> RecordWeights(const records::RecordSet& records,
                                                  size_t vossel_count, double vossel_size_m,
                                                  const WeightingProfile& profile);

/// §7 fusion: for every vossel and channel, C_k = Σ w C / Σ w and
/// U_k = sqrt(Σ w (C − C_k)² / Σ w) ⊕ 1/sqrt(Σ w) (the spread taken over the channels' mean),
/// with w from WeightKernel. Reads records only: no visibility, projection or image sampling.
/// `records` must be sorted by vossel. Parallel over vossels (TBB).
/// Reweighting a stored project is this call with another profile.
absl::StatusOr<records::FusedValues> Fuse(const records::RecordSet& records, size_t vossel_count,
                                          double vossel_size_m, const WeightingProfile& profile);

}  // namespace vasl::fusion

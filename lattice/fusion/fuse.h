/// @file fuse.h
/// @brief Fusion and reweighting (VASL-MODEL §7): one pass over the records.
#pragma once

#include <vector>

#include "absl/status/statusor.h"
#include "lattice/fusion/profile.h"
#include "lattice/records/records.h"

namespace vasl::fusion {

/// The channel a record fuses into: derived records fuse into the RGB channels they edit (§10),
/// every other modality into its own (§7).
inline records::Modality FusedChannelOf(records::Modality m) {
  return m == records::Modality::kDerived ? records::Modality::kRgb : m;
}

/// Offsets of each vossel's records in a RecordSet sorted by vossel: vossel k's records are
/// [begin[k], begin[k+1]). INTERNAL when the records are not sorted by a valid index.
absl::StatusOr<std::vector<size_t>> VosselOffsets(const records::RecordSet& records,
                                                  size_t vossel_count);

/// The §7 weight of every record under `profile`, with the vossel offsets it used.
struct RecordWeightsResult {
  std::vector<size_t> begin;  ///< vossel_count + 1 offsets (VosselOffsets)
  std::vector<float> weight;  ///< w_{k,m} per record; 0 for invalidated records
};

/// w_{k,m} (RecordWeight) of every record, one parallel pass; the proximity term's r_{k,min} is
/// taken per vossel and channel. Fusion and the §8 view blend both weigh records through this.
absl::StatusOr<RecordWeightsResult> RecordWeights(const records::RecordSet& records,
                                                  size_t vossel_count, double vossel_size_m,
                                                  const WeightingProfile& profile);

/// §7 fusion: for every vossel and channel, C_k = Σ w C / Σ w and
/// U_k = sqrt(Σ w (C − C_k)² / Σ w) ⊕ 1/sqrt(Σ w) (the spread taken over the channels' mean),
/// with w from RecordWeight. Reads records only: no visibility, projection or image sampling.
/// `records` must be sorted by vossel. Parallel over vossels (TBB).
/// Reweighting a stored project is this call with another profile.
absl::StatusOr<records::FusedValues> Fuse(const records::RecordSet& records, size_t vossel_count,
                                          double vossel_size_m, const WeightingProfile& profile);

}  // namespace vasl::fusion

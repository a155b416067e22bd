/// @file reweight_flow.h
/// @brief The reweight flow (VASL-MODEL §7): a new version whose tiles hold fused values under
///        a profile, made from the stored records alone.
/// @details This module links the store and the fusion library only: no visibility,
///          projection or image sampling can run here (tests/reweight checks it at link time).
#pragma once

#include <cstdint>
#include <functional>
#include <string>

#include "absl/status/statusor.h"
#include "lattice/fusion/profile.h"
#include "lattice/store/project_store.h"

namespace vasl::reweight {

/// What a reweight made.
struct ReweightResult {
  int64_t version = 0;        ///< the new version (HEAD's when nothing had to change)
  std::string layer;          ///< the fused layer (store::FusedLayerName)
  std::string profile;        ///< the profile's name and revision
  int32_t revision = 0;
  int64_t tiles = 0;          ///< tiles fused
  int64_t records = 0;        ///< records read
  int64_t vossels = 0;        ///< vossels fused
  int64_t bytes_written = 0;  ///< bytes of the fused objects written
  bool unchanged = false;     ///< HEAD already held the layer on every tile: no new version
  double seconds = 0.0;
  /// A retry (Engine::Reweight's request id): the reweight had committed `version` under the
  /// id and was not done again; `answer` is what the caller recorded with it (may be empty).
  bool replayed = false;
  std::string answer;
};

/// Called after each tile: tiles done, tiles in all. A status other than OK stops the reweight
/// with that status before its commit (the tiles in flight finish; no other tile starts).
using TileProgressFn = std::function<absl::Status(int64_t done, int64_t total)>;

/// Reweights HEAD under `profile`: for every tile, reads its records object, fuses them (§7,
/// fusion::Fuse) and writes the tile's fused layer for the profile; then commits a version
/// whose manifest shares every other object with HEAD. One pass over the records, parallel
/// over tiles (TBB), memory bounded by the tiles in flight. The fused tiles equal, bit for bit,
/// those a fresh ingest of the same scans makes under the profile.
/// FAILED_PRECONDITION for a project without versions.
/// @warning The caller serialises it with the project's other writers.
absl::StatusOr<ReweightResult> Reweight(store::ProjectStore& store,
                                        const fusion::WeightingProfile& profile,
                                        const TileProgressFn& progress = {});

}  // namespace vasl::reweight

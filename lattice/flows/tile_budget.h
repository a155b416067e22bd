/// @file tile_budget.h
/// @brief What a reader holds of a version in memory, estimated from its manifest, and the
///        groups of tiles a render or a records query reads one after another so that what it
///        holds at once stays within a byte budget (issue "A store that grows": bounded memory).
/// @details The estimate counts the arrays a loaded tile fills (records::VosselGeometry with
///          its sums and frames, its index grid, each fused layer, records::RecordSet) from the
///          manifest's vossel and record counts; it reads no tile file.
#pragma once

#include <cstdint>
#include <map>
#include <set>
#include <string>
#include <vector>

#include "lattice/store/project_store.h"

namespace vasl::flows {

/// Estimated bytes a tile with these layers fills once loaded: its geometry, `fused_layers`
/// fused layers and, `with_records`, its records with the per-record arrays a weighing adds.
int64_t TileMemoryBytes(const std::map<std::string, store::ManifestEntry>& layers,
                        bool with_records, int fused_layers);

/// TileMemoryBytes summed over the manifest's tiles (`among`: only those; null: all).
int64_t VersionMemoryBytes(const store::Manifest& manifest, bool with_records, int fused_layers,
                           const std::set<tiles::TileKey>* among = nullptr);

/// The manifest's tiles (`among`: only those; null: all) in groups, in key order, each of
/// which fits `budget_bytes` by TileMemoryBytes; a tile larger than the budget alone is a group
/// of its own. Empty for no tiles.
std::vector<std::set<tiles::TileKey>> TileGroups(const store::Manifest& manifest,
                                                 bool with_records, int fused_layers,
                                                 int64_t budget_bytes,
                                                 const std::set<tiles::TileKey>* among = nullptr);

/// A tile's box: the cells of its vossels, lattice metres, and its distance from an eye.
struct TileBox {
  double near_m = 0.0;  ///< from the eye to the box (0: the eye is inside)
  tiles::TileKey key;
  Eigen::Vector3d lo_m, hi_m;
};
/// The manifest's tiles, nearest `eye_m` first (then by key), for tiles of `tile_vossels`
/// vossels of edge `vossel_size_m`.
std::vector<TileBox> TilesNearestFirst(const store::Manifest& manifest,
                                       const Eigen::Vector3d& eye_m, int tile_vossels,
                                       double vossel_size_m);

/// The manifest's tiles that hold a vossel whose cell meets the index box [lo, hi] (inclusive
/// vossel coordinates), for tiles of `tile_vossels`.
std::set<tiles::TileKey> TilesMeeting(const store::Manifest& manifest, const openvdb::Coord& lo,
                                      const openvdb::Coord& hi, int tile_vossels);

}  // namespace vasl::flows

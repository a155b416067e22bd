/// @file tile_split.h
/// @brief Cutting a project's in-memory arrays (geometry, records, fused values) into tiles and
///        putting tiles back together. A tile's contents are plain records:: structures with
///        tile-local vossel indices, in the canonical order of the tile's own index grid, so
///        that record_grid.h writes each tile as ordinary OpenVDB files.
#pragma once

#include <map>
#include <set>
#include <string>
#include <vector>

#include "lattice/records/records.h"
#include "lattice/tiles/tiling.h"

namespace vasl::tiles {

/// One tile of a version.
struct TileContents {
  TileKey key;
  records::VosselGeometry geometry;  ///< the tile's vossels, tile-local canonical order
  records::RecordSet records;        ///< sorted by (tile-local vossel, scan)
  records::FusedValues fused;        ///< per tile-local vossel, under the default profile
  /// Fused values under other profiles, by layer name (store::FusedLayerName).
  std::map<std::string, records::FusedValues> profile_fused;
};

/// The tile of every vossel of `geometry`.
std::vector<TileKey> TilesOfVossels(const records::VosselGeometry& geometry, int tile_vossels);

/// Vossel indices of `geometry` grouped by tile (ascending within a tile).
std::map<TileKey, std::vector<int32_t>> VosselsByTile(const records::VosselGeometry& geometry,
                                                       int tile_vossels);

/// The contents of the tiles `keys` cut out of whole-project arrays (`records` sorted by vossel;
/// `fused` and each of `profile_fused` per vossel of `geometry`, may be empty). A tile's fused
/// values hold exactly the channels its own records fuse into (records::FusedChannelOf), as
/// fusing the tile alone gives them. Tiles without vossels come back empty. Parallel (TBB).
std::vector<TileContents> ExtractTiles(
    const records::VosselGeometry& geometry, const records::RecordSet& records,
    const records::FusedValues& fused, const std::set<TileKey>& keys, int tile_vossels,
    const std::map<std::string, records::FusedValues>* profile_fused = nullptr);

/// ExtractTiles one tile at a time, the whole-project index (vossels by tile, each vossel's
/// first record) built once: for a writer that holds only the tiles it is writing. The arrays
/// it was made from must outlive it. Cut is thread-safe.
class TileCutter {
 public:
  TileCutter(const records::VosselGeometry& geometry, const records::RecordSet& records,
             const records::FusedValues& fused, int tile_vossels,
             const std::map<std::string, records::FusedValues>* profile_fused = nullptr);
  TileContents Cut(const TileKey& key) const;
  /// The vossels tile `key` holds.
  size_t VosselsOf(const TileKey& key) const;

 private:
  const records::VosselGeometry& geometry_;
  const records::RecordSet& records_;
  const records::FusedValues& fused_;
  const std::map<std::string, records::FusedValues>* profile_fused_;
  std::map<TileKey, std::vector<int32_t>> by_tile_;
  std::vector<size_t> begin_;  ///< first record of every vossel, and the end
};

/// Whole-project arrays put together from tiles: vossels in canonical order of one index grid,
/// records sorted by vossel (then scan), fused values per vossel. The tiles are consumed.
struct Assembled {
  records::VosselGeometry geometry;
  records::RecordSet records;
  records::FusedValues fused;
  std::map<std::string, records::FusedValues> profile_fused;  ///< layers every tile holds
};
Assembled AssembleTiles(std::vector<TileContents>&& tiles, double vossel_size_m);

/// AssembleTiles one tile at a time, for a reader that frees each tile as it arrives: Add
/// appends a tile's vossels and records and frees them (its fused values wait for Finish);
/// `vossels` and `records` are the totals to expect (capacity). Tiles come in any order; the
/// result is the same.
class TileAssembler {
 public:
  TileAssembler(double vossel_size_m, size_t vossels, size_t records);
  void Add(TileContents&& tile);
  Assembled Finish();

 private:
  size_t vossels_ = 0;
  Assembled out_;
  std::vector<size_t> tile_first_;
  std::vector<records::FusedValues> fused_;
  std::vector<std::map<std::string, records::FusedValues>> profile_fused_;
};

}  // namespace vasl::tiles

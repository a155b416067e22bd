/// @file vdb_io.h
/// @brief Internal helpers of the records module: one-time OpenVDB initialisation, file IO of
///        grids with OpenVDB exceptions converted to absl::Status at this boundary.
/// @details Not part of the public API (namespace vasl::records::internal).
#pragma once

#include <filesystem>
#include <string>
#include <vector>

#include <openvdb/openvdb.h>

#include "absl/status/statusor.h"

namespace vasl::records::internal {

/// Calls openvdb::initialize() exactly once per process (std::call_once). Thread-safe.
void EnsureOpenVdbInitialized();

/// Replaces the random UUID OpenVDB writes in a file's header (`bytes`, the whole file) by one
/// derived from the file's own bytes, so that equal contents give equal files (tile objects are
/// content-addressed: equal tiles must hash equal). Called by WriteVdbFile. `where` names the
/// file in errors.
absl::Status MakeUuidDeterministic(std::string& bytes, const std::string& where);

/// How a file's leaf values are compressed. Both keep OpenVDB's active-mask scheme (inactive
/// values are not stored); kBlosc adds blosc (zip where blosc is absent) on each leaf.
/// OpenVDB 10 compresses every leaf of a plain grid twice (once to size it for the file's
/// delayed-load metadata, once to write it), and on values that barely compress (the exact
/// double sums of a geometry tile: 4% smaller) that is a third of the writer's time for
/// nothing; kActiveMaskOnly is for such grids.
enum class VdbCompression { kBlosc, kActiveMaskOnly };

/// Whether each grid of a file carries OpenVDB's statistics (file_bbox_min/max,
/// file_voxel_count, file_mem_bytes: what `vdb_print -l` and `-m` show). OpenVDB computes them
/// in passes over the whole tree as it writes: a sixth of a geometry tile's encoding. A tile
/// object's are read by nothing (the manifest counts its vossels and records); a file a user
/// opens (an export) keeps them.
enum class VdbGridStats { kWrite, kSkip };

/// The bytes of a .vdb file of `grids` with file-level `meta`, its UUID deterministic
/// (MakeUuidDeterministic): what WriteVdbFile writes, for a caller that puts them elsewhere
/// (a tile object). Errors: INTERNAL naming `where` with the OpenVDB message.
absl::StatusOr<std::string> EncodeVdbFile(const openvdb::GridCPtrVec& grids,
                                          const openvdb::MetaMap& meta,
                                          VdbCompression compression, const std::string& where,
                                          VdbGridStats stats = VdbGridStats::kWrite);

/// Writes `grids` with file-level `meta` to `path`, compressed as `compression` says.
/// Errors: INTERNAL with the path and the OpenVDB message.
absl::Status WriteVdbFile(const std::filesystem::path& path, const openvdb::GridCPtrVec& grids,
                          const openvdb::MetaMap& meta = openvdb::MetaMap(),
                          VdbCompression compression = VdbCompression::kBlosc);

/// The contents of one .vdb file, fully loaded (no delayed loading).
struct VdbFileContents {
  openvdb::GridPtrVecPtr grids;  ///< every grid in the file
  openvdb::MetaMap::Ptr meta;    ///< file-level metadata
};

/// Reads every grid of `path`. `delay_load` keeps point attribute data on disk (used when only
/// descriptors are needed). Errors: NOT_FOUND if the file is missing, DATA_LOSS if OpenVDB
/// cannot parse it (message carries the path and the OpenVDB text).
absl::StatusOr<VdbFileContents> ReadVdbFile(const std::filesystem::path& path,
                                            bool delay_load = false);
/// Reads only the grids of `path` named in `names` (OpenVDB seeks past the others); a name the
/// file lacks is left out of the result. Errors as ReadVdbFile.
absl::StatusOr<VdbFileContents> ReadVdbGrids(const std::filesystem::path& path,
                                             const std::vector<std::string>& names);

/// Checks that `index` numbers its active voxels 0..n-1 in leaf order, then voxel offset (the
/// canonical vossel order of records.h); returns n. FAILED_PRECONDITION naming `where` if not.
absl::StatusOr<size_t> CheckCanonicalOrder(const openvdb::Int32Grid& index,
                                           const std::string& where);

/// The grid named `name` in `contents`, or nullptr.
openvdb::GridBase::Ptr FindGrid(const VdbFileContents& contents, const std::string& name);

}  // namespace vasl::records::internal

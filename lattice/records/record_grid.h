/// @file record_grid.h
/// @brief The records of a version as an OpenVDB PointDataGrid, and the geometry and fused
///        values as plain OpenVDB grids (VASL-MODEL §6, RECORDS-NOTES.md).
/// @details records.vdb holds one PointDataGrid "records": one point per record, position left
///          uniform (records sit at vossel centres), attributes per §6 with quantising codecs.
///          geometry.vdb holds "index" (Int32), "count" (Int32), "centroid" (Vec3s, world m),
///          "normal" (Vec3s), "covariance_diag"/"covariance_off" (Vec3s, m²).
///          fused-<profile>.vdb holds per modality "<modality>.value" (Vec3s or float),
///          "<modality>.weight" and "<modality>.uncertainty" (float).
///          Tile objects (EncodeGeometry, EncodeFused) keep the same arrays as the attributes of
///          one PointDataGrid, a point per vossel. All open in `vdb_print`, Houdini and
///          pyopenvdb.
#pragma once

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "lattice/records/records.h"

namespace vasl::records {

/// Writes geometry (all vossels) to `path` (geometry.vdb).
absl::Status WriteGeometry(const VosselGeometry& geometry, const std::filesystem::path& path);
/// Reads geometry.vdb or a geometry object (EncodeGeometry; older objects kept plain grids as
/// geometry.vdb does); rebuilds the index grid and the flat arrays in vossel order. A file with
/// the exact sums and without centroid and covariance (a geometry object) has them derived from
/// its sums (FrameOf), the bits an ingest derived before writing it.
absl::StatusOr<VosselGeometry> ReadGeometry(const std::filesystem::path& path);
/// Reads only the lattice of geometry.vdb: the index grid and the vossel coordinates, which is
/// all that reading records (ReadRecords) and writing fused values (WriteFused) take; the other
/// grids of the file are skipped unread (a reweight's case).
absl::StatusOr<VosselGeometry> ReadLattice(const std::filesystem::path& path);

/// Writes the records as a PointDataGrid to `path` (records.vdb), blosc-compressed.
/// `records` must be sorted by vossel (RecordSet::SortByVossel).
absl::Status WriteRecords(const VosselGeometry& geometry, const RecordSet& records,
                          const std::filesystem::path& path);
/// Rounds every field of `records` to what its codec stores (half, 8- and 16-bit fixed point),
/// exactly as WriteRecords then ReadRecords would. The flows round records as they make them,
/// so fusion at ingest reads the same values a later reweight reads from disk and both give the
/// same bits (VASL-MODEL §7). Idempotent.
void RoundToStorage(RecordSet& records);

/// The half-precision bits of `n` floats, as Imath's half(float) gives them (to nearest, ties
/// to even): the records' half attributes (value, footprint) are stored so. With F16C where
/// the CPU has it, the same bits.
void EncodeHalves(const float* in, uint16_t* out, size_t n);

/// Reads records.vdb back into flat arrays (sorted by vossel), given the version's geometry.
absl::StatusOr<RecordSet> ReadRecords(const VosselGeometry& geometry,
                                      const std::filesystem::path& path);
/// Lists the attributes of the PointDataGrid in `path` with type, codec and stride.
absl::StatusOr<std::vector<AttributeInfo>> ListRecordAttributes(const std::filesystem::path& path);

/// Writes / reads fused values (fused-<profile>.vdb).
absl::Status WriteFused(const VosselGeometry& geometry, const FusedValues& fused,
                        const std::filesystem::path& path);
absl::StatusOr<FusedValues> ReadFused(const VosselGeometry& geometry,
                                      const std::filesystem::path& path);

/// The bytes of tile objects, for a writer that stores them elsewhere (tile objects go into
/// the object store from memory): what WriteRecords and WriteFused write, and the geometry
/// object. Geometry and fused objects keep OpenVDB's active-mask compression alone, records add
/// blosc (README "Storage"). Their grids carry no statistics metadata (internal::VdbGridStats).
/// A geometry object holds the "index" grid and a PointDataGrid "vossels" with one point per
/// vossel at its voxel's centre and its arrays as attributes ("count", "normal", "sum",
/// "sum_xx", "view_sum", "frame_count", "frame_centroid", "frame_covariance", "frame_view",
/// "frame_normal"; "centroid" and "covariance" only without the sums, which give them): one
/// tree to write and read instead of a grid per array (BM_EncodeGeometry, README "Storage").
/// A fused object likewise holds a PointDataGrid "fused", a point per vossel with per modality
/// "<modality>_value" (stride 1 or 3), "_weight" and "_uncertainty" (zeros where the weight is
/// not > 0, as the fused file's inactive voxels read). ReadGeometry and ReadFused read these
/// and the plain grids of older objects alike.
absl::StatusOr<std::string> EncodeGeometry(const VosselGeometry& geometry);
absl::StatusOr<std::string> EncodeRecords(const VosselGeometry& geometry,
                                          const RecordSet& records);
absl::StatusOr<std::string> EncodeFused(const VosselGeometry& geometry, const FusedValues& fused);

/// The grids of the files above, for writers that put several layers in one file (export):
/// the geometry grids (a plain grid per array the geometry has, as geometry.vdb holds them), the
/// "records" PointDataGrid and the fused grids. `where` names the data in error messages.
absl::StatusOr<openvdb::GridCPtrVec> GeometryGrids(const VosselGeometry& geometry,
                                                   const std::string& where);
absl::StatusOr<openvdb::GridBase::Ptr> RecordsGrid(const VosselGeometry& geometry,
                                                   const RecordSet& records,
                                                   const std::string& where);
absl::StatusOr<openvdb::GridCPtrVec> FusedGrids(const VosselGeometry& geometry,
                                                const FusedValues& fused);

/// Writes one self-contained OpenVDB file holding every layer of a version: the geometry grids,
/// the "records" PointDataGrid and the fused grids (export, for tools that want one file).
/// Every grid's transform is translated by `origin_m` (kept as metadata "origin_m"), so that
/// the file places vossels in world coordinates (VASL-MODEL §1).
absl::Status WriteVersionFile(const VosselGeometry& geometry, const RecordSet& records,
                              const FusedValues& fused, const std::filesystem::path& path,
                              const Eigen::Vector3d& origin_m = Eigen::Vector3d::Zero());

/// Rebuilds `geometry.index_grid` and renumbers vossels into canonical order (leaf order, then
/// voxel offset) from `geometry.coord`; returns old→new index map. Arrays are permuted.
std::vector<int32_t> CanonicalizeVosselOrder(VosselGeometry& geometry);

/// What InsertVossels did: where each vossel went.
struct VosselInsertion {
  std::vector<int32_t> old_to_new;    ///< per vossel of the base: its index now (ascending)
  std::vector<int32_t> added_to_new;  ///< per coordinate added: the index of its vossel
  std::vector<uint8_t> created;       ///< per coordinate added: 1 where it made the vossel
};

/// `base`, whose vossels are in canonical order, with a vossel made at each coordinate of
/// `added` it lacks, written to `out` in canonical order: what CanonicalizeVosselOrder gives of
/// base's arrays with the new vossels appended, but from a copy of base's index tree (its
/// topology is not built again) and with each array written once, since inserting vossels
/// keeps the order of those already there. A made vossel takes zero counts, sums, centroid,
/// normal and covariance and a default frame. An array of base shorter than its vossels is
/// filled so (as resizing it would). `out` must not be `&base`.
VosselInsertion InsertVossels(const VosselGeometry& base,
                              const std::vector<openvdb::Coord>& added, VosselGeometry* out);

}  // namespace vasl::records

/// @file records.h
/// @brief In-memory layout of one project version: vossel geometry (VASL-MODEL §1), the
///        observation records (§6) and the fused values (§7), as flat arrays.
/// @details Hot loops (fusion, reweight, render) read these contiguous arrays. On disk the same
///          data lives in OpenVDB files (records.vdb: a PointDataGrid, one point per record;
///          geometry.vdb and fused-<profile>.vdb: plain grids), see record_grid.h.
///
///          Vossel order: vossel indices run over the index grid's leaf nodes in tree order and,
///          inside a leaf, in voxel-offset order. Records are sorted by vossel index (then by
///          scan), so that each leaf's records are contiguous per voxel in offset order, which is
///          exactly what a PointDataGrid needs (RECORDS-NOTES pitfall 2).
#pragma once

#include <array>
#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include <Eigen/Core>
#include <openvdb/openvdb.h>

namespace vasl::records {

/// What kind of observation a record holds (§6). The integer values are stored on disk.
enum class Modality : int8_t {
  kUnspecified = 0,
  kLidar = 1,    ///< LiDAR return: value[0] = intensity
  kRgb = 2,      ///< RGB camera: value[0..2] = linear R, G, B
  kIr = 3,       ///< infrared camera: value[0]
  kRadar = 4,    ///< radar amplitude: value[0]
  kDerived = 5,  ///< back-projected (§10): value[0..2] = R, G, B
};
inline constexpr int kModalityCount = 6;

/// Channels a modality fills in `value`.
inline int ChannelCount(Modality m) { return (m == Modality::kRgb || m == Modality::kDerived) ? 3 : 1; }
const char* ModalityName(Modality m);

/// The fused channel a record's modality fuses into (§7): derived records fuse into the RGB
/// channels they edit (§10), every other modality into its own.
inline Modality FusedChannelOf(Modality m) { return m == Modality::kDerived ? Modality::kRgb : m; }

/// Bits of RecordSet::flags (§6).
enum RecordFlag : int8_t {
  kFlagDerived = 1 << 0,      ///< derived (back-projected) rather than raw
  kFlagInvalidated = 1 << 1,  ///< excluded by a hard invalidation (e.g. flare)
};

/// Confidence factors kept apart per record (§6, §9), each in [0, 1]: one per artefact, so a
/// profile weights each by its own κ. Smear and fog came after the first four; records stored
/// before them read as 1 there (not measured).
enum ConfidenceFactor : int {
  kConfSaturation = 0,  ///< clipped pixels and their blooming halo
  kConfFlare = 1,       ///< veiling glare around bright sources
  kConfDirt = 2,        ///< lens dirt, D < 1 (at fusion, from the rig's lens map)
  kConfCodec = 3,       ///< JPEG blocking, ringing and chroma subsampling
  kConfSmear = 4,       ///< readout smear along a clipped source's columns
  kConfFog = 5,         ///< an additive veil (fog, haze), v > 0 (at fusion, from the lens map)
};
inline constexpr int kConfidenceCount = 6;
/// Their names, in factor order (profiles' κ, the API's conf).
inline constexpr const char* kConfidenceNames[kConfidenceCount] = {"saturation", "flare", "dirt",
                                                                   "codec", "smear", "fog"};
inline constexpr int kValueChannels = 3;

/// Exact running sums of the points that fell in one vossel (§1), the state that makes merging
/// a new scan's points exact: count lives in VosselGeometry::point_count. Positions are taken
/// relative to the vossel centre h·k, so doubles keep sub-micrometre precision on any site.
/// Scans add their sums in source-id order; a rebuild adds them in the same order, so both
/// give the same bits.
struct VosselSums {
  Eigen::Vector3d sum_m = Eigen::Vector3d::Zero();       ///< Σ (x − h·k), metres
  std::array<double, 6> sum_xx_m2 = {0, 0, 0, 0, 0, 0};  ///< Σ (x − h·k)(x − h·k)ᵀ: xx, xy, xz, yy, yz, zz
  Eigen::Vector3d view_sum = Eigen::Vector3d::Zero();    ///< Σ unit vectors from each point to its sensor

  /// Adds `other` (another scan's sums of the same vossel).
  void Add(const VosselSums& other) {
    sum_m += other.sum_m;
    for (int i = 0; i < 6; ++i) sum_xx_m2[i] += other.sum_xx_m2[i];
    view_sum += other.view_sum;
  }
  bool operator==(const VosselSums& o) const {
    return sum_m == o.sum_m && sum_xx_m2 == o.sum_xx_m2 && view_sum == o.view_sum;
  }
};

/// The record frame of one vossel (VASL-MODEL §5-§6, choice): the surface estimate of the
/// first LiDAR, in source-id order, whose returns fell in it. Visibility, sampling and every
/// geometric term of a record (range, incidence, footprint, uv) are evaluated on the frame, not
/// on the surface of all scans (VosselGeometry::centroid_m, normal), because appending a scan
/// moves the surface of nearly every vossel it sees by a little and would otherwise change every
/// older record there. A frame is set when its vossel appears and changes only when a vossel of
/// its neighbourhood appears or vanishes (its normal) or when its own LiDAR is deleted; so an
/// ingest revisits older sources only where the new geometry comes in front of them (§5), and
/// the records still equal a rebuild's, which merges the LiDARs in the same order.
struct VosselFrame {
  int32_t count = 0;                                     ///< that LiDAR's returns in the vossel
  Eigen::Vector3f centroid_m = Eigen::Vector3f::Zero();  ///< their mean, world metres
  std::array<float, 6> covariance_m2 = {0, 0, 0, 0, 0, 0};  ///< their covariance (xx … zz)
  Eigen::Vector3f view = Eigen::Vector3f::Zero();        ///< Σ unit vectors to that LiDAR
  /// PCA over the frames of the 3×3×3 neighbourhood, oriented by `view` (ComputeNormals).
  Eigen::Vector3f normal = Eigen::Vector3f::Zero();
  bool operator==(const VosselFrame& o) const {
    return count == o.count && centroid_m == o.centroid_m && covariance_m2 == o.covariance_m2 &&
           view == o.view && normal == o.normal;
  }
  bool operator!=(const VosselFrame& o) const { return !(*this == o); }
};

/// The surface estimate of `count` points with sums `s` in vossel k (§1): centroid h·k + Σ/n,
/// covariance Σxxᵀ/n − μμᵀ, view Σ unit vectors to the sensors; normal left zero. The one
/// implementation: an ingest derives each vossel's surface and new frames with it, and a
/// geometry object, which keeps the sums and not what they give, is read back through it.
VosselFrame FrameOf(const openvdb::Coord& k, int32_t count, const VosselSums& s,
                    double vossel_size_m);

/// Geometry of the vossels of one version (§1), indexed by vossel index.
struct VosselGeometry {
  /// Vossel edge h, metres; the grid transform is createLinearTransform(h) (cell-centred).
  double vossel_size_m = 0.02;
  /// Active voxel value = vossel index; background -1. Its topology is the lattice.
  openvdb::Int32Grid::Ptr index_grid;
  /// Index-space coordinate k of each vossel; its centre is h·k (§1).
  std::vector<openvdb::Coord> coord;
  /// Number of measured points that fell in the vossel, all scans.
  std::vector<int32_t> point_count;
  /// Mean of the points in the vossel, world metres.
  std::vector<Eigen::Vector3f> centroid_m;
  /// Unit surface normal from PCA over the neighbourhood (§1); zero when undetermined.
  std::vector<Eigen::Vector3f> normal;
  /// Position covariance of the points in the vossel, world m², (xx, xy, xz, yy, yz, zz).
  std::vector<std::array<float, 6>> covariance_m2;
  /// Running sums of the vossel's points (count in point_count); centroid and covariance are
  /// derived from them (DeriveCentroidAndCovariance). Empty for geometry without sums.
  std::vector<VosselSums> sums;
  /// The record frame of each vossel (VosselFrame). Empty for geometry built by hand or read
  /// from a store written before frames: the surface is then the frame.
  std::vector<VosselFrame> frame;

  size_t size() const { return coord.size(); }
  /// Where records of vossel k are evaluated: its frame's centroid and normal (zero: none).
  const Eigen::Vector3f& FrameCentroid(size_t k) const {
    return frame.empty() ? centroid_m[k] : frame[k].centroid_m;
  }
  const Eigen::Vector3f& FrameNormal(size_t k) const {
    return frame.empty() ? normal[k] : frame[k].normal;
  }
};

/// §1: centroid h·k + Σ/n and covariance Σxxᵀ/n − μμᵀ of every vossel of `geometry`, which
/// must carry counts and sums, from them (FrameOf): after a merge of scans, and when a geometry
/// object that keeps the sums alone is read (ReadGeometry). With `only`, of the vossels it marks
/// alone (those a merge touched: the others keep what was derived from their sums before).
void DeriveCentroidAndCovariance(VosselGeometry& geometry,
                                 const std::vector<uint8_t>* only = nullptr);

/// The observation records of a version (§6), structure of arrays, sorted by (vossel, scan).
struct RecordSet {
  std::vector<int32_t> vossel;        ///< vossel index into VosselGeometry
  std::vector<int32_t> scan;          ///< observation source id (catalog `sources.id`)
  std::vector<int8_t> modality;       ///< Modality
  std::vector<float> value;           ///< kValueChannels per record, linear radiometry
  std::vector<float> range_m;         ///< r_{k,m}, metres
  std::vector<float> cos_inc;         ///< cosθ_{k,m} in [0, 1]
  std::vector<float> foot_major_m;    ///< s_major, metres (§3)
  std::vector<float> foot_minor_m;    ///< s_minor, metres (§3)
  /// 2 per record: continuous pixel coords in the source image; stored in 16 bits, steps of
  /// 16384/65535 px (≈ 0.25 px) within [0, 16384) px (record_grid.cc: kUvUnitPx)
  std::vector<float> uv_px;
  std::vector<float> vis;             ///< V_{k,m} in [0, 1] (§5)
  std::vector<float> conf;            ///< kConfidenceCount per record, each in [0, 1] (§9)
  std::vector<int8_t> flags;          ///< RecordFlag bits
  std::vector<int32_t> batch;         ///< ingest or back-projection batch id

  size_t size() const { return vossel.size(); }
  void Reserve(size_t n);
  void Resize(size_t n);
  /// Appends every record of `other`.
  void Append(const RecordSet& other);
  /// Reorders the records by (vossel, scan, modality); stable.
  void SortByVossel();
  /// The records at `indices`, in that order; room for `capacity` records reserved (appending
  /// up to it then copies nothing already there).
  RecordSet Select(const std::vector<size_t>& indices, size_t capacity = 0) const;
};

/// The records `rows` of `kept` (in increasing order), their vossels renumbered by
/// `renumber[vossel]`, and the records of `added`, as one set sorted by (vossel, scan,
/// modality): what Select, Append and SortByVossel give, with each record copied once (a
/// change keeps most of a project's records and adds a few). Stable: on equal keys the kept
/// records come first, then the added ones in their order. When the renumbered kept rows are
/// out of order (a renumbering that does not keep the vossels' order) it sorts them too.
RecordSet MergeRenumbered(const RecordSet& kept, const std::vector<size_t>& rows,
                          const std::vector<int32_t>& renumber, RecordSet added);

/// Fused values of one modality under one profile (§7), per vossel.
struct FusedModality {
  int channels = 0;
  std::vector<float> value;        ///< channels per vossel: C_k
  std::vector<float> weight;       ///< Σ_m w_{k,m}; 0 where the vossel has no usable record
  std::vector<float> uncertainty;  ///< U_k (§7)
};

/// All fused values of a version under one weighting profile (§7).
struct FusedValues {
  std::string profile;                     ///< profile name
  std::map<Modality, FusedModality> by_modality;
};

}  // namespace vasl::records

namespace vasl::records {

/// One attribute of the record PointDataGrid as stored on disk (what `vasl inspect` lists).
struct AttributeInfo {
  std::string name;   ///< attribute name, e.g. "range"
  std::string type;   ///< value type name, e.g. "float", "vec3s", "int16"
  std::string codec;  ///< codec name, e.g. "null", "trnc", "ufxpt8"
  int stride = 1;     ///< values per record
};

}  // namespace vasl::records

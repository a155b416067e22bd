// records.vdb: the observation records of a version (VASL-MODEL §6) as one OpenVDB
// PointDataGrid, built directly leaf by leaf (RECORDS-NOTES "Pitfalls of the API").
#include "lattice/records/record_grid.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <exception>
#include <limits>
#include <memory>
#include <string>
#include <type_traits>
#include <vector>

#include <Imath/half.h>
#if defined(__x86_64__)
#include <immintrin.h>
#endif
#include <openvdb/openvdb.h>
#include <openvdb/points/AttributeArray.h>
#include <openvdb/points/AttributeSet.h>
#include <openvdb/points/PointDataGrid.h>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "lattice/memory/isa.h"
#include "lattice/records/point_attributes.h"
#include "lattice/records/vdb_io.h"

namespace vasl::records {
namespace {

namespace pts = openvdb::points;
using openvdb::Index;
using openvdb::Int32Grid;
using pts::PointDataGrid;
using pts::PointDataTree;
using PointLeaf = PointDataTree::LeafNodeType;

// Registered OpenVDB 10 attribute types only (RECORDS-NOTES pitfall 1).
using internal::RawArray;
using internal::Tag;
using PositionArray = RawArray<openvdb::Vec3f>;
using Int8Array = RawArray<int8_t>;
using Int16Array = RawArray<int16_t>;
using Int32Array = RawArray<int32_t>;
using FloatArray = RawArray<float>;
using HalfArray = pts::TypedAttributeArray<float, pts::TruncateCodec>;
using Unit8Array = pts::TypedAttributeArray<float, pts::FixedPointCodec<true, pts::UnitRange>>;
using Unit16Array = pts::TypedAttributeArray<float, pts::FixedPointCodec<false, pts::UnitRange>>;

/// Storage of one attribute on disk.
enum class Kind { kInt8, kInt16, kInt32, kFloat, kHalf, kUnit8, kUnit16 };

/// Conversion between record values and raw attribute storage. Our own encoders replace the
/// codecs' encode so that fixed-point values ROUND (RECORDS-NOTES pitfall 6: OpenVDB's
/// FixedPointCodec truncates, turning vis = 0.5 into 0.498); decoding matches the codecs'.
template <typename ArrayT>
struct Storage;
template <typename IntT>
struct IntStorage {
  using S = IntT;
  template <typename V>
  static S Encode(V v) { return static_cast<S>(v); }
  static IntT Decode(S s) { return s; }
};
template <> struct Storage<Int8Array> : IntStorage<int8_t> {};
template <> struct Storage<Int16Array> : IntStorage<int16_t> {};
template <> struct Storage<Int32Array> : IntStorage<int32_t> {};
template <>
struct Storage<FloatArray> {
  using S = float;
  template <typename V>
  static S Encode(V v) { return static_cast<float>(v); }
  static float Decode(S s) { return s; }
};
template <>
struct Storage<HalfArray> {
  using S = openvdb::math::half;
  template <typename V>
  static S Encode(V v) { return S(static_cast<float>(v)); }  // round to nearest
  static float Decode(S s) { return static_cast<float>(s); }
};
template <typename UIntT>
struct UnitStorage {
  using S = UIntT;
  static constexpr float kMax = static_cast<float>(std::numeric_limits<UIntT>::max());
  /// [0, 1] -> round(v·max); below 0 and NaN -> 0, above 1 -> max. Error ≤ 0.5 / max.
  template <typename V>
  static S Encode(V v) {
    const float f = static_cast<float>(v);
    if (!(f > 0.0f)) return 0;
    if (f >= 1.0f) return std::numeric_limits<UIntT>::max();
    // std::lround(p) for 0 < p <= max, without its libm call per value: p + 0.5 is exact in
    // double and truncation rounds a positive value down, so the loops below vectorise.
    const float p = f * kMax;
    return static_cast<S>(static_cast<int32_t>(double(p) + 0.5));
  }
  static float Decode(S s) { return static_cast<float>(s) / kMax; }
};
template <> struct Storage<Unit8Array> : UnitStorage<uint8_t> {};
template <> struct Storage<Unit16Array> : UnitStorage<uint16_t> {};

#if VASL_ISA_VARIANTS
// Eight at a time with F16C (every AVX2 CPU has it), rounding to nearest, ties to even, as
// Imath's imath_float_to_half; a NaN lane is converted by Imath (F16C quiets a signalling
// NaN, Imath keeps its payload), so that an object's bytes do not depend on the machine.
__attribute__((target("avx,f16c"))) void EncodeHalvesF16c(const float* in, uint16_t* out,
                                                           size_t n) {
  size_t k = 0;
  for (; k + 8 <= n; k += 8) {
    const __m256 v = _mm256_loadu_ps(in + k);
    _mm_storeu_si128(reinterpret_cast<__m128i*>(out + k),
                     _mm256_cvtps_ph(v, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC));
    if (_mm256_movemask_ps(_mm256_cmp_ps(v, v, _CMP_UNORD_Q)) != 0) {
      for (size_t j = k; j < k + 8; ++j) {
        if (std::isnan(in[j])) out[j] = imath_float_to_half(in[j]);
      }
    }
  }
  for (; k < n; ++k) out[k] = imath_float_to_half(in[k]);
}
#endif

}  // namespace

void EncodeHalves(const float* in, uint16_t* out, size_t n) {
#if VASL_ISA_VARIANTS
  if (memory::WidestIsa() >= memory::Isa::kAvx2 && __builtin_cpu_supports("f16c")) {
    EncodeHalvesF16c(in, out, n);
    return;
  }
#endif
  for (size_t k = 0; k < n; ++k) out[k] = imath_float_to_half(in[k]);
}

namespace {

/// Calls `fn(Tag<ArrayT>{})` for the attribute array type of `kind`.
template <typename Fn>
void Dispatch(Kind kind, Fn&& fn) {
  switch (kind) {
    case Kind::kInt8: return fn(Tag<Int8Array>{});
    case Kind::kInt16: return fn(Tag<Int16Array>{});
    case Kind::kInt32: return fn(Tag<Int32Array>{});
    case Kind::kFloat: return fn(Tag<FloatArray>{});
    case Kind::kHalf: return fn(Tag<HalfArray>{});
    case Kind::kUnit8: return fn(Tag<Unit8Array>{});
    case Kind::kUnit16: return fn(Tag<Unit16Array>{});
  }
}

/// The kind whose registered type name pair is `type`, if any.
bool KindOf(const openvdb::NamePair& type, Kind* kind) {
  for (Kind k : {Kind::kInt8, Kind::kInt16, Kind::kInt32, Kind::kFloat, Kind::kHalf,
                 Kind::kUnit8, Kind::kUnit16}) {
    bool match = false;
    Dispatch(k, [&](auto tag) { match = decltype(tag)::type::attributeType() == type; });
    if (match) {
      *kind = k;
      return true;
    }
  }
  return false;
}

/// Calls `fn(name, array, stride, preferred kind)` for every record attribute (§6), in file
/// order. The preferred kind is narrowed (int32 -> int16) or widened (half -> float) per file
/// by the value range, see ChooseKind.
template <typename RS, typename Fn>
void ForEachAttribute(RS& r, Fn&& fn) {
  fn("scan", r.scan, 1, Kind::kInt32);
  fn("modality", r.modality, 1, Kind::kInt8);
  fn("value", r.value, kValueChannels, Kind::kHalf);
  fn("range", r.range_m, 1, Kind::kFloat);  // h/10 or better to 300 m: half errs 2.4 cm at 50 m
  fn("cos_inc", r.cos_inc, 1, Kind::kUnit16);
  fn("foot_major", r.foot_major_m, 1, Kind::kHalf);
  fn("foot_minor", r.foot_minor_m, 1, Kind::kHalf);
  fn("uv", r.uv_px, 2, Kind::kUnit16);  // in units of kUvUnitPx (UnitOf): a quarter pixel
  fn("vis", r.vis, 1, Kind::kUnit8);
  fn("conf", r.conf, kConfidenceCount, Kind::kUnit8);
  fn("flags", r.flags, 1, Kind::kInt8);
  fn("batch", r.batch, 1, Kind::kInt32);
}

/// The pixel coordinates of a record's sample are stored as 16-bit fractions of this span
/// (16384 = 2^14 px, so that scaling is exact in float): steps of 0.25 px, for images up to
/// 16384 px wide. They place a sample in its image for the lens model (§7), whose terms vary
/// over hundreds of pixels; a file with a coordinate outside [0, 16384) keeps float.
constexpr float kUvUnitPx = 16384.0f;

/// What a stored value of 1 of attribute `name` stands for in the record: kUvUnitPx for the
/// pixel coordinates in a fixed-point kind, 1 otherwise.
float UnitOf(const char* name, Kind kind) {
  return (kind == Kind::kUnit8 || kind == Kind::kUnit16) && std::strcmp(name, "uv") == 0
             ? kUvUnitPx
             : 1.0f;
}

/// int32 ids are stored as int16 when every value fits; half is widened to float when a finite
/// value exceeds the half range (65504), e.g. raw LiDAR intensities; a scaled fixed-point
/// attribute (UnitOf) is widened to float when a value lies outside [0, its unit).
template <typename T>
Kind ChooseKind(const std::vector<T>& a, Kind preferred, float unit) {
  if (unit != 1.0f) {
    for (T v : a) {
      if (!(v >= 0.0f && v < unit)) return Kind::kFloat;
    }
    return preferred;
  }
  if (preferred == Kind::kInt32) {
    for (T v : a) {
      if (v < std::numeric_limits<int16_t>::min() || v > std::numeric_limits<int16_t>::max()) {
        return Kind::kInt32;
      }
    }
    return Kind::kInt16;
  }
  if (preferred == Kind::kHalf) {
    constexpr float kHalfMax = 65504.0f;
    for (T v : a) {
      const float f = std::fabs(static_cast<float>(v));
      if (std::isfinite(f) && f > kHalfMax) return Kind::kFloat;
    }
  }
  return preferred;
}

}  // namespace

void RoundToStorage(RecordSet& records) {
  ForEachAttribute(records, [](const char* name, auto& values, int, Kind kind) {
    using T = typename std::decay_t<decltype(values)>::value_type;
    if constexpr (std::is_floating_point_v<T>) {
      if (kind == Kind::kHalf) {
        for (T& v : values) {
          // Values past the half range stay float: ChooseKind widens such a file to float.
          if (std::fabs(v) <= 65504.0f) v = Storage<HalfArray>::Decode(Storage<HalfArray>::Encode(v));
        }
      } else if (kind == Kind::kUnit8 || kind == Kind::kUnit16) {
        Dispatch(kind, [&](auto tag) {
          using S = Storage<typename decltype(tag)::type>;
          if constexpr (std::is_same_v<typename S::S, uint8_t> || std::is_same_v<typename S::S, uint16_t>) {
            const float unit = UnitOf(name, kind), inv = 1.0f / unit;  // powers of two: exact
            if (unit == 1.0f) {
              for (T& v : values) v = S::Decode(S::Encode(v));
            } else {
              // Values outside [0, unit) stay float: ChooseKind widens such a file to float.
              for (T& v : values) {
                if (v >= 0.0f && v < unit) v = S::Decode(S::Encode(float(v) * inv)) * unit;
              }
            }
          }
        });
      }
    }
  });
}

namespace {

std::string AttributeListMeta(const std::vector<AttributeInfo>& infos) {
  std::string s;
  for (const AttributeInfo& a : infos) {
    absl::StrAppend(&s, s.empty() ? "" : ";", a.name, ":", a.type, ":", a.codec, ":", a.stride);
  }
  return s;
}

struct PlannedAttribute {
  std::string name;
  Kind kind;
  int stride;
  size_t pos = 0;       ///< position in the attribute set
  int stored_stride = 0;  ///< values per record in the file: `stride`, or fewer (older conf)
  float unit = 1.0f;      ///< what a stored 1 stands for (UnitOf)
};

/// Confidence factors a file written before the record's conf widened lacks (§9): values it
/// has in its first columns, factors it does not know are 1 (not measured).
constexpr const char* kWidenedAttribute = "conf";

openvdb::MetaMap RecordsFileMeta() {
  openvdb::MetaMap meta;
  meta.insertMeta("vasl_file", openvdb::StringMetadata("records"));
  return meta;
}

}  // namespace

absl::Status WriteRecords(const VosselGeometry& geometry, const RecordSet& records,
                          const std::filesystem::path& path) {
  absl::StatusOr<openvdb::GridBase::Ptr> grid = RecordsGrid(geometry, records, path.string());
  if (!grid.ok()) return grid.status();
  return internal::WriteVdbFile(path, {*grid}, RecordsFileMeta());
}

absl::StatusOr<std::string> EncodeRecords(const VosselGeometry& geometry,
                                          const RecordSet& records) {
  constexpr char kWhere[] = "records object";
  absl::StatusOr<openvdb::GridBase::Ptr> grid = RecordsGrid(geometry, records, kWhere);
  if (!grid.ok()) return grid.status();
  return internal::EncodeVdbFile({*grid}, RecordsFileMeta(), internal::VdbCompression::kBlosc,
                                 kWhere, internal::VdbGridStats::kSkip);
}

absl::StatusOr<openvdb::GridBase::Ptr> RecordsGrid(const VosselGeometry& geometry,
                                                   const RecordSet& records,
                                                   const std::string& where) {
  internal::EnsureOpenVdbInitialized();
  const std::filesystem::path path(where);
  if (!geometry.index_grid) {
    return absl::InvalidArgumentError("WriteRecords: the geometry has no index grid");
  }
  const Int32Grid& index = *geometry.index_grid;
  absl::StatusOr<size_t> vossel_count = internal::CheckCanonicalOrder(index, path.string());
  if (!vossel_count.ok()) return vossel_count.status();
  const size_t n = records.size();

  // Validate the record arrays: sizes, vossel range, sort order.
  absl::Status bad;
  ForEachAttribute(records, [&](const char* name, const auto& a, int stride, Kind) {
    if (bad.ok() && a.size() != n * stride) {
      bad = absl::InvalidArgumentError(absl::StrCat("WriteRecords: attribute ", name, " has ",
                                                    a.size(), " values; expected ", n * stride));
    }
  });
  if (!bad.ok()) return bad;
  for (size_t i = 0; i < n; ++i) {
    const int32_t v = records.vossel[i];
    if (v < 0 || static_cast<size_t>(v) >= *vossel_count) {
      return absl::InvalidArgumentError(absl::StrCat("WriteRecords: record ", i, " has vossel ",
                                                     v, " outside [0, ", *vossel_count, ")"));
    }
    if (i > 0 && v < records.vossel[i - 1]) {
      return absl::InvalidArgumentError(absl::StrCat(
          "WriteRecords: records are not sorted by vossel (record ", i,
          "); call RecordSet::SortByVossel first"));
    }
  }

  std::vector<PlannedAttribute> plan;
  ForEachAttribute(records, [&](const char* name, const auto& a, int stride, Kind preferred) {
    plan.push_back({name, ChooseKind(a, preferred, UnitOf(name, preferred)), stride});
  });

  try {
    // Prototype attribute set: stride is not carried by the descriptor (pitfall 3), so the
    // prototype's arrays carry it and each leaf copies the prototype.
    auto descriptor = pts::AttributeSet::Descriptor::create(PositionArray::attributeType());
    pts::AttributeSet prototype(descriptor, 1);
    std::vector<AttributeInfo> infos;
    infos.push_back({"P", PositionArray::attributeType().first,
                     PositionArray::attributeType().second, 1});
    for (PlannedAttribute& a : plan) {
      Dispatch(a.kind, [&](auto tag) {
        using ArrayT = typename decltype(tag)::type;
        prototype.appendAttribute(a.name, ArrayT::attributeType(), a.stride);
        infos.push_back({a.name, ArrayT::attributeType().first, ArrayT::attributeType().second,
                         a.stride});
      });
      a.pos = prototype.find(a.name);
    }

    // Leaves of the index grid in tree order = vossel order; each one's records are a
    // contiguous slice of the sorted arrays.
    std::vector<const Int32Grid::TreeType::LeafNodeType*> index_leaves;
    index_leaves.reserve(index.tree().leafCount());
    for (auto it = index.tree().cbeginLeaf(); it; ++it) index_leaves.push_back(it.getLeaf());
    std::vector<size_t> first_record(index_leaves.size() + 1, n);
    {
      int32_t vossel_start = 0;
      for (size_t i = 0; i < index_leaves.size(); ++i) {
        first_record[i] = static_cast<size_t>(
            std::lower_bound(records.vossel.begin(), records.vossel.end(), vossel_start) -
            records.vossel.begin());
        vossel_start += static_cast<int32_t>(index_leaves[i]->onVoxelCount());
      }
    }

    std::vector<std::unique_ptr<PointLeaf>> point_leaves(index_leaves.size());
    {
      // One registry lock for all leaves built in parallel (pitfall 5).
      pts::AttributeArray::ScopedRegistryLock lock;
      tbb::parallel_for(
          tbb::blocked_range<size_t>(0, index_leaves.size(), 8),
          [&](const tbb::blocked_range<size_t>& r) {
            for (size_t li = r.begin(); li < r.end(); ++li) {
              const size_t begin = first_record[li];
              const size_t end = first_record[li + 1];
              if (begin == end) continue;  // a leaf without records is left out
              const auto* index_leaf = index_leaves[li];
              // Records per voxel: vossel -> voxel offset inside this leaf.
              std::vector<Index> counts(PointLeaf::SIZE, 0);
              std::vector<Index> pos_of;  // vossel - first vossel of the leaf -> offset
              pos_of.reserve(index_leaf->onVoxelCount());
              for (auto it = index_leaf->cbeginValueOn(); it; ++it) pos_of.push_back(it.pos());
              const int32_t vossel0 = index_leaf->cbeginValueOn() ? *index_leaf->cbeginValueOn()
                                                                  : 0;
              for (size_t k = begin; k < end; ++k) {
                ++counts[pos_of[records.vossel[k] - vossel0]];
              }
              // A voxel's value is the end offset of its records (pitfall 2).
              std::vector<PointDataTree::ValueType> offsets(PointLeaf::SIZE);
              Index running = 0;
              for (Index o = 0; o < PointLeaf::SIZE; ++o) offsets[o] = running += counts[o];

              const Index count = static_cast<Index>(end - begin);
              auto set = std::make_unique<pts::AttributeSet>(prototype, count, &lock);
              ForEachAttribute(records, [&](const char* name, const auto& src, int stride,
                                            Kind) {
                const PlannedAttribute* a = nullptr;
                for (const PlannedAttribute& p : plan) {
                  if (p.name == name) a = &p;
                }
                Dispatch(a->kind, [&](auto tag) {
                  using ArrayT = typename decltype(tag)::type;
                  using St = Storage<ArrayT>;
                  auto& array = static_cast<ArrayT&>(*set->get(a->pos));
                  array.expand(/*fill=*/false);
                  // The array was just created for this leaf and is not shared: writing its
                  // raw buffer is safe and skips the codec's truncating encode (pitfall 6).
                  auto* out = const_cast<typename St::S*>(array.constData());
                  const auto* in = src.data() + begin * stride;
                  const size_t values = size_t(count) * stride;
                  if constexpr (std::is_same_v<ArrayT, HalfArray> &&
                                std::is_same_v<std::decay_t<decltype(*in)>, float>) {
                    static_assert(sizeof(typename St::S) == sizeof(uint16_t));
                    EncodeHalves(in, reinterpret_cast<uint16_t*>(out), values);
                  } else if (const float unit = UnitOf(name, a->kind); unit == 1.0f) {
                    for (size_t k = 0; k < values; ++k) out[k] = St::Encode(in[k]);
                  } else {
                    const float inv = 1.0f / unit;
                    for (size_t k = 0; k < values; ++k) out[k] = St::Encode(float(in[k]) * inv);
                  }
                });
              });
              auto leaf = std::make_unique<PointLeaf>(index_leaf->origin());
              leaf->replaceAttributeSet(set.release(), /*allowMismatchingDescriptors=*/true);
              leaf->setOffsets(offsets, /*updateValueMask=*/true);
              point_leaves[li] = std::move(leaf);
            }
          });
    }

    auto tree = std::make_shared<PointDataTree>();
    for (auto& leaf : point_leaves) {
      if (leaf) tree->addLeaf(leaf.release());
    }
    auto grid = PointDataGrid::create(tree);
    grid->setTransform(index.transform().copy());
    grid->setName("records");
    grid->insertMeta("vasl_attributes", openvdb::StringMetadata(AttributeListMeta(infos)));
    grid->insertMeta("record_count", openvdb::Int64Metadata(static_cast<int64_t>(n)));
    return openvdb::GridBase::Ptr(grid);
  } catch (const std::exception& e) {
    return absl::InternalError(
        absl::StrCat("WriteRecords: OpenVDB failed building ", path.string(), ": ", e.what()));
  }
}

absl::StatusOr<RecordSet> ReadRecords(const VosselGeometry& geometry,
                                      const std::filesystem::path& path) {
  if (!geometry.index_grid) {
    return absl::InvalidArgumentError("ReadRecords: the geometry has no index grid");
  }
  absl::StatusOr<internal::VdbFileContents> contents = internal::ReadVdbFile(path);
  if (!contents.ok()) return contents.status();
  auto grid = openvdb::GridBase::grid<PointDataGrid>(internal::FindGrid(*contents, "records"));
  if (!grid) {
    return absl::DataLossError(
        absl::StrCat(path.string(), " has no PointDataGrid named \"records\""));
  }
  const Int32Grid& index = *geometry.index_grid;
  try {
    std::vector<PointLeaf*> leaves;
    for (auto it = grid->tree().beginLeaf(); it; ++it) leaves.push_back(it.getLeaf());
    std::vector<size_t> first(leaves.size() + 1, 0);
    for (size_t i = 0; i < leaves.size(); ++i) first[i + 1] = first[i] + leaves[i]->getLastValue();
    const size_t n = first.back();

    // Resolve each attribute's position and storage kind once, from the first leaf.
    std::vector<PlannedAttribute> plan;
    RecordSet out;
    absl::Status bad;
    if (!leaves.empty()) {
      const pts::AttributeSet& set = leaves[0]->attributeSet();
      ForEachAttribute(out, [&](const char* name, auto&, int stride, Kind) {
        if (!bad.ok()) return;
        const size_t pos = set.find(name);
        Kind kind;
        if (pos == pts::AttributeSet::INVALID_POS) {
          bad = absl::DataLossError(absl::StrCat(path.string(), ": attribute \"", name,
                                                 "\" is missing"));
        } else if (!KindOf(set.descriptor().type(pos), &kind)) {
          bad = absl::DataLossError(absl::StrCat(path.string(), ": attribute \"", name,
                                                 "\" has an unsupported type ",
                                                 set.descriptor().type(pos).first, "/",
                                                 set.descriptor().type(pos).second));
        } else if (const int stored = static_cast<int>(set.getConst(pos)->stride());
                   stored != stride &&
                   !(std::string(name) == kWidenedAttribute && stored >= 1 && stored < stride)) {
          bad = absl::DataLossError(absl::StrCat(path.string(), ": attribute \"", name,
                                                 "\" has stride ", stored, "; expected ",
                                                 stride));
        } else {
          plan.push_back({name, kind, stride, pos, stored, UnitOf(name, kind)});
        }
      });
    }
    if (!bad.ok()) return bad;
    out.Resize(n);

    std::atomic<bool> mismatch{false};
    tbb::parallel_for(
        tbb::blocked_range<size_t>(0, leaves.size(), 8), [&](const tbb::blocked_range<size_t>& r) {
          Int32Grid::ConstAccessor acc(index.tree());
          for (size_t li = r.begin(); li < r.end(); ++li) {
            PointLeaf& leaf = *leaves[li];
            const auto* index_leaf = acc.probeConstLeaf(leaf.origin());
            if (!index_leaf) {
              mismatch = true;
              return;
            }
            // vossel of each record from the index leaf at the same voxel.
            size_t k = first[li];
            Index prev_end = 0;
            for (Index o = 0; o < PointLeaf::SIZE; ++o) {
              const Index end = leaf.getValue(o);
              if (end == prev_end) continue;
              if (!index_leaf->isValueOn(o) || end < prev_end) {
                mismatch = true;
                return;
              }
              std::fill(out.vossel.begin() + k, out.vossel.begin() + k + (end - prev_end),
                        index_leaf->getValue(o));
              k += end - prev_end;
              prev_end = end;
            }
            const size_t begin = first[li];
            const size_t count = first[li + 1] - begin;
            // Every leaf's attributes as the first leaf's, where the plan found them (a file
            // read shares one descriptor between its leaves: no name is looked up per leaf).
            const pts::AttributeSet::Descriptor& descriptor = leaf.attributeSet().descriptor();
            if (&descriptor != &leaves[0]->attributeSet().descriptor() &&
                !(descriptor == leaves[0]->attributeSet().descriptor())) {
              mismatch = true;
              return;
            }
            size_t planned = 0;  // ForEachAttribute's order, as the plan's
            ForEachAttribute(out, [&](const char*, auto& dst, int stride, Kind) {
              const PlannedAttribute* a = &plan[planned++];
              const size_t pos = a->pos;
              Dispatch(a->kind, [&](auto tag) {
                using ArrayT = typename decltype(tag)::type;
                using St = Storage<ArrayT>;
                using Elem = typename std::decay_t<decltype(dst)>::value_type;
                auto& array = static_cast<ArrayT&>(leaf.attributeArray(pos));
                array.loadData();
                if (array.isUniform()) array.expand();
                const auto* in = array.constData();
                Elem* o = dst.data() + begin * stride;
                if (const float unit = a->unit; unit != 1.0f) {
                  const size_t values = count * stride;  // scaled kinds: uv, never widened
                  for (size_t v = 0; v < values; ++v) {
                    o[v] = static_cast<Elem>(St::Decode(in[v]) * unit);
                  }
                } else if (a->stored_stride == stride) {
                  const size_t values = count * stride;
                  for (size_t v = 0; v < values; ++v) o[v] = static_cast<Elem>(St::Decode(in[v]));
                } else {
                  for (size_t r = 0; r < count; ++r) {
                    for (int c = 0; c < stride; ++c) {
                      o[r * stride + c] = c < a->stored_stride
                          ? static_cast<Elem>(St::Decode(in[r * a->stored_stride + c]))
                          : Elem(1);
                    }
                  }
                }
              });
            });
          }
        });
    if (mismatch) {
      return absl::DataLossError(absl::StrCat(
          path.string(), " does not match the version's geometry (records in voxels that are "
                         "not vossels, or attribute sets that differ between leaves)"));
    }
    return out;
  } catch (const std::exception& e) {
    return absl::DataLossError(
        absl::StrCat("ReadRecords: OpenVDB failed reading ", path.string(), ": ", e.what()));
  }
}

absl::StatusOr<std::vector<AttributeInfo>> ListRecordAttributes(
    const std::filesystem::path& path) {
  absl::StatusOr<internal::VdbFileContents> contents =
      internal::ReadVdbFile(path, /*delay_load=*/true);
  if (!contents.ok()) return contents.status();
  auto grid = openvdb::GridBase::grid<PointDataGrid>(internal::FindGrid(*contents, "records"));
  if (!grid) {
    return absl::DataLossError(
        absl::StrCat(path.string(), " has no PointDataGrid named \"records\""));
  }
  std::vector<AttributeInfo> infos;
  auto leaf = grid->tree().cbeginLeaf();
  if (leaf) {
    // Descriptor order = position order; stride lives on the arrays (pitfall 3).
    const pts::AttributeSet& set = leaf->attributeSet();
    const auto& descriptor = set.descriptor();
    infos.resize(descriptor.size());
    for (const auto& [name, pos] : descriptor.map()) {
      const openvdb::NamePair& type = descriptor.type(pos);
      infos[pos] = {name, type.first, type.second,
                    static_cast<int>(set.getConst(pos)->stride())};
    }
    return infos;
  }
  // No leaf (no records): the attribute list written in the grid metadata.
  auto meta = grid->getMetadata<openvdb::StringMetadata>("vasl_attributes");
  if (!meta) return infos;
  for (absl::string_view item : absl::StrSplit(meta->value(), ';', absl::SkipEmpty())) {
    std::vector<std::string> f = absl::StrSplit(item, ':');
    AttributeInfo info;
    if (f.size() != 4 || !absl::SimpleAtoi(f[3], &info.stride)) {
      return absl::DataLossError(absl::StrCat(path.string(),
                                              ": malformed vasl_attributes metadata"));
    }
    info.name = f[0];
    info.type = f[1];
    info.codec = f[2];
    infos.push_back(std::move(info));
  }
  return infos;
}

absl::Status WriteVersionFile(const VosselGeometry& geometry, const RecordSet& records,
                              const FusedValues& fused, const std::filesystem::path& path,
                              const Eigen::Vector3d& origin_m) {
  absl::StatusOr<openvdb::GridCPtrVec> grids = GeometryGrids(geometry, path.string());
  if (!grids.ok()) return grids.status();
  absl::StatusOr<openvdb::GridBase::Ptr> recs = RecordsGrid(geometry, records, path.string());
  if (!recs.ok()) return recs.status();
  absl::StatusOr<openvdb::GridCPtrVec> fused_grids = FusedGrids(geometry, fused);
  if (!fused_grids.ok()) return fused_grids.status();
  grids->push_back(*recs);
  grids->insert(grids->end(), fused_grids->begin(), fused_grids->end());
  const openvdb::Vec3d origin(origin_m.x(), origin_m.y(), origin_m.z());
  for (openvdb::GridBase::ConstPtr& grid : *grids) {  // shallow copies: trees are shared
    openvdb::math::Transform::Ptr world = grid->transform().copy();
    world->postTranslate(origin);
    grid = grid->copyGridReplacingTransform(world);
  }
  openvdb::MetaMap meta;
  meta.insertMeta("vasl_file", openvdb::StringMetadata("version"));
  meta.insertMeta("origin_m", openvdb::Vec3DMetadata(origin));
  meta.insertMeta("vossel_size_m", openvdb::DoubleMetadata(geometry.vossel_size_m));
  meta.insertMeta("profile", openvdb::StringMetadata(fused.profile));
  meta.insertMeta("record_count", openvdb::Int64Metadata(static_cast<int64_t>(records.size())));
  return internal::WriteVdbFile(path, *grids, meta);
}

}  // namespace vasl::records

// Vossel order (records.h), geometry.vdb and fused-<profile>.vdb (record_grid.h): plain OpenVDB
// grids that share the topology of the index grid (VASL-MODEL §1, §7); geometry and fused tile
// objects: the same arrays as attributes of one PointDataGrid, a point per vossel.
#include <algorithm>
#include <array>
#include <atomic>
#include <cstring>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <type_traits>
#include <vector>

#include <openvdb/openvdb.h>
#include <openvdb/points/AttributeArray.h>
#include <openvdb/points/AttributeSet.h>
#include <openvdb/points/PointDataGrid.h>
#include <openvdb/tools/Prune.h>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_invoke.h>
#include <tbb/parallel_reduce.h>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "lattice/records/point_attributes.h"
#include "lattice/records/record_grid.h"
#include "lattice/records/vdb_io.h"

namespace vasl::records {
namespace {

using openvdb::Coord;
using openvdb::Int32Grid;
using openvdb::Int32Tree;
using Int32Leaf = Int32Tree::LeafNodeType;

constexpr size_t kGrain = 16384;

/// Leaves of `tree` in tree order (the order that defines vossel numbering).
template <typename TreeT>
std::vector<typename TreeT::LeafNodeType*> LeavesInOrder(TreeT& tree) {
  std::vector<typename TreeT::LeafNodeType*> leaves;
  leaves.reserve(tree.leafCount());
  for (auto it = tree.beginLeaf(); it; ++it) leaves.push_back(it.getLeaf());
  return leaves;
}
template <typename TreeT>
std::vector<const typename TreeT::LeafNodeType*> ConstLeavesInOrder(const TreeT& tree) {
  std::vector<const typename TreeT::LeafNodeType*> leaves;
  leaves.reserve(tree.leafCount());
  for (auto it = tree.cbeginLeaf(); it; ++it) leaves.push_back(it.getLeaf());
  return leaves;
}

/// Gathers `out[j] = in[inverse[j]]` for a per-vossel array with `stride` values per vossel;
/// an empty array stays empty.
template <typename T>
void Gather(std::vector<T>& array, const std::vector<int32_t>& inverse) {
  if (array.empty()) return;
  std::vector<T> out(inverse.size());
  tbb::parallel_for(tbb::blocked_range<size_t>(0, inverse.size(), kGrain),
                    [&](const tbb::blocked_range<size_t>& r) {
                      for (size_t j = r.begin(); j < r.end(); ++j) out[j] = array[inverse[j]];
                    });
  array.swap(out);
}

/// Collects the first error raised by parallel workers.
class FirstError {
 public:
  void Set(absl::Status s) {
    if (failed_.exchange(true)) return;
    std::lock_guard<std::mutex> lock(mu_);
    status_ = std::move(s);
  }
  bool failed() const { return failed_.load(std::memory_order_relaxed); }
  absl::Status status() {
    std::lock_guard<std::mutex> lock(mu_);
    return status_;
  }

 private:
  std::atomic<bool> failed_{false};
  std::mutex mu_;
  absl::Status status_;
};

/// A grid of type GridT over the topology of `index`, voxel value `value_of(vossel)`; voxels
/// whose vossel fails `keep(vossel)` are made inactive with value zero. Leaves of a topology
/// copy come in the same order as the source's, so leaves pair up by position.
template <typename GridT, typename Fn, typename Keep>
typename GridT::Ptr GridOverVossels(const Int32Grid& index, const std::string& name,
                                    Fn&& value_of, Keep&& keep) {
  using TreeT = typename GridT::TreeType;
  using ValueT = typename GridT::ValueType;
  auto tree = std::make_shared<TreeT>(index.tree(), openvdb::zeroVal<ValueT>(),
                                      openvdb::TopologyCopy());
  const auto src = ConstLeavesInOrder(index.tree());
  auto dst = LeavesInOrder(*tree);
  tbb::parallel_for(tbb::blocked_range<size_t>(0, src.size(), 16),
                    [&](const tbb::blocked_range<size_t>& r) {
                      for (size_t i = r.begin(); i < r.end(); ++i) {
                        for (auto it = src[i]->cbeginValueOn(); it; ++it) {
                          if (keep(*it)) {
                            dst[i]->setValueOnly(it.pos(), value_of(*it));
                          } else {
                            dst[i]->setValueOff(it.pos(), openvdb::zeroVal<ValueT>());
                          }
                        }
                      }
                    });
  auto grid = GridT::create(tree);
  grid->setTransform(index.transform().copy());
  grid->setName(name);
  grid->setGridClass(openvdb::GRID_UNKNOWN);
  return grid;
}
template <typename GridT, typename Fn>
typename GridT::Ptr GridOverVossels(const Int32Grid& index, const std::string& name,
                                    Fn&& value_of) {
  return GridOverVossels<GridT>(index, name, std::forward<Fn>(value_of),
                                [](int32_t) { return true; });
}

/// Calls `fn(vossel, value)` for every active voxel of `grid` (leaf voxels only), in parallel.
/// A voxel outside the lattice of `index` is DATA_LOSS.
template <typename GridT, typename Fn>
absl::Status ForEachActiveVossel(const Int32Grid& index, const GridT& grid,
                                 const std::filesystem::path& path, Fn&& fn) {
  const auto leaves = ConstLeavesInOrder(grid.tree());
  FirstError error;
  tbb::parallel_for(
      tbb::blocked_range<size_t>(0, leaves.size(), 16), [&](const tbb::blocked_range<size_t>& r) {
        Int32Grid::ConstAccessor acc(index.tree());
        for (size_t i = r.begin(); i < r.end() && !error.failed(); ++i) {
          const Int32Leaf* index_leaf = acc.probeConstLeaf(leaves[i]->origin());
          for (auto it = leaves[i]->cbeginValueOn(); it; ++it) {
            const int32_t vossel = index_leaf ? index_leaf->getValue(it.pos()) : -1;
            if (vossel < 0 || (index_leaf && !index_leaf->isValueOn(it.pos()))) {
              error.Set(absl::DataLossError(absl::StrCat(
                  path.string(), ": grid \"", grid.getName(), "\" has an active voxel at ",
                  it.getCoord().asVec3i().str(), " which is not a vossel of the geometry")));
              return;
            }
            fn(vossel, *it);
          }
        }
      });
  return error.status();
}

template <typename GridT>
typename GridT::Ptr GridAs(const internal::VdbFileContents& contents, const std::string& name) {
  return openvdb::GridBase::grid<GridT>(internal::FindGrid(contents, name));
}

absl::Status CheckArraySize(size_t got, size_t n, size_t stride, const char* what) {
  if (got == 0 || got == n * stride) return absl::OkStatus();
  return absl::InvalidArgumentError(absl::StrCat("geometry array ", what, " has ", got,
                                                 " values; expected 0 or ", n * stride, " (",
                                                 n, " vossels x ", stride, ")"));
}

// A covariance (xx, xy, xz, yy, yz, zz) is stored as two Vec3s grids: `<name>_diag`
// (xx, yy, zz) and `<name>_off` (xy, xz, yz); `covariance_of(v)` gives vossel v's.
template <typename CovarianceOf>
void PushCovarianceGrids(openvdb::GridCPtrVec& grids, const Int32Grid& index,
                         const std::string& name, CovarianceOf covariance_of) {
  using openvdb::Vec3f;
  grids.push_back(GridOverVossels<openvdb::Vec3SGrid>(index, name + "_diag", [&](int32_t v) {
    const std::array<float, 6>& c = covariance_of(v);
    return Vec3f(c[0], c[3], c[5]);
  }));
  grids.push_back(GridOverVossels<openvdb::Vec3SGrid>(index, name + "_off", [&](int32_t v) {
    const std::array<float, 6>& c = covariance_of(v);
    return Vec3f(c[1], c[2], c[4]);
  }));
}

// The covariance PushCovarianceGrids stored as `diag` and `off`.
std::array<float, 6> CovarianceFrom(const Eigen::Vector3f& diag, const Eigen::Vector3f& off) {
  return {diag.x(), off.x(), off.y(), diag.y(), off.z(), diag.z()};
}

}  // namespace

namespace internal {
absl::StatusOr<size_t> CheckCanonicalOrder(const Int32Grid& index, const std::string& where) {
  const auto leaves = ConstLeavesInOrder(index.tree());
  std::vector<size_t> start(leaves.size() + 1, 0);
  for (size_t i = 0; i < leaves.size(); ++i) start[i + 1] = start[i] + leaves[i]->onVoxelCount();
  std::atomic<bool> ok{true};
  tbb::parallel_for(tbb::blocked_range<size_t>(0, leaves.size(), 16),
                    [&](const tbb::blocked_range<size_t>& r) {
                      for (size_t i = r.begin(); i < r.end(); ++i) {
                        int64_t expect = static_cast<int64_t>(start[i]);
                        for (auto it = leaves[i]->cbeginValueOn(); it; ++it, ++expect) {
                          if (*it != expect) ok = false;
                        }
                      }
                    });
  if (!ok) {
    return absl::FailedPreconditionError(absl::StrCat(
        where, ": the index grid does not number vossels in canonical order (leaf order, then "
               "voxel offset); call CanonicalizeVosselOrder first"));
  }
  return start.back();
}
}  // namespace internal

namespace {

/// Numbers the active voxels of `tree` in canonical order: leaf order, then voxel offset.
void NumberInCanonicalOrder(Int32Tree& tree) {
  auto leaves = LeavesInOrder(tree);
  std::vector<int32_t> start(leaves.size() + 1, 0);
  for (size_t i = 0; i < leaves.size(); ++i) {
    start[i + 1] = start[i] + static_cast<int32_t>(leaves[i]->onVoxelCount());
  }
  tbb::parallel_for(tbb::blocked_range<size_t>(0, leaves.size(), 16),
                    [&](const tbb::blocked_range<size_t>& r) {
                      for (size_t i = r.begin(); i < r.end(); ++i) {
                        int32_t next = start[i];
                        for (auto it = leaves[i]->beginValueOn(); it; ++it) it.setValue(next++);
                      }
                    });
}

/// The index grid of a numbered tree, over the lattice of edge `h`.
Int32Grid::Ptr IndexGridOf(Int32Tree::Ptr tree, double h) {
  auto grid = Int32Grid::create(tree);
  grid->setTransform(openvdb::math::Transform::createLinearTransform(h));
  grid->setName("index");
  grid->setGridClass(openvdb::GRID_UNKNOWN);
  return grid;
}

}  // namespace

std::vector<int32_t> CanonicalizeVosselOrder(VosselGeometry& geometry) {
  internal::EnsureOpenVdbInitialized();
  const std::vector<Coord>& coord = geometry.coord;
  const size_t n = coord.size();

  // Topology: per-thread trees joined by topology union.
  struct TopologyBody {
    const std::vector<Coord>* coord;
    Int32Tree tree{-1};
    explicit TopologyBody(const std::vector<Coord>* c) : coord(c) {}
    TopologyBody(TopologyBody& other, tbb::split) : coord(other.coord) {}
    void operator()(const tbb::blocked_range<size_t>& r) {
      Int32Grid::Accessor acc(tree);
      for (size_t i = r.begin(); i < r.end(); ++i) acc.setValueOn((*coord)[i], 0);
    }
    void join(TopologyBody& other) { tree.topologyUnion(other.tree); }
  } body(&coord);
  tbb::parallel_reduce(tbb::blocked_range<size_t>(0, n, kGrain), body);
  auto tree = std::make_shared<Int32Tree>(-1);
  tree->topologyUnion(body.tree);

  NumberInCanonicalOrder(*tree);

  // old -> new map, then new -> old (first occurrence wins for duplicated coordinates).
  std::vector<int32_t> old_to_new(n);
  tbb::parallel_for(tbb::blocked_range<size_t>(0, n, kGrain),
                    [&](const tbb::blocked_range<size_t>& r) {
                      Int32Grid::ConstAccessor acc(*tree);
                      for (size_t i = r.begin(); i < r.end(); ++i) {
                        old_to_new[i] = acc.getValue(coord[i]);
                      }
                    });
  const size_t m = static_cast<size_t>(tree->activeVoxelCount());
  std::vector<int32_t> new_to_old(m, -1);
  for (size_t i = 0; i < n; ++i) {
    int32_t& slot = new_to_old[old_to_new[i]];
    if (slot < 0) slot = static_cast<int32_t>(i);
  }

  Gather(geometry.coord, new_to_old);
  if (geometry.point_count.size() == n) Gather(geometry.point_count, new_to_old);
  if (geometry.centroid_m.size() == n) Gather(geometry.centroid_m, new_to_old);
  if (geometry.normal.size() == n) Gather(geometry.normal, new_to_old);
  if (geometry.covariance_m2.size() == n) Gather(geometry.covariance_m2, new_to_old);
  if (geometry.sums.size() == n) Gather(geometry.sums, new_to_old);
  if (geometry.frame.size() == n) Gather(geometry.frame, new_to_old);

  geometry.index_grid = IndexGridOf(tree, geometry.vossel_size_m);
  return old_to_new;
}

namespace {

/// Appends base[begin, end) to `out`, `fill` where base is shorter.
template <typename T>
void AppendRun(std::vector<T>& out, const std::vector<T>& base, size_t begin, size_t end,
               const T& fill) {
  const size_t have = std::min(end, std::max(begin, base.size()));
  out.insert(out.end(), base.begin() + std::ptrdiff_t(begin), base.begin() + std::ptrdiff_t(have));
  out.insert(out.end(), end - have, fill);
}

}  // namespace

VosselInsertion InsertVossels(const VosselGeometry& base, const std::vector<Coord>& added,
                              VosselGeometry* out) {
  internal::EnsureOpenVdbInitialized();
  const size_t n = base.size();
  VosselInsertion ins;
  ins.added_to_new.assign(added.size(), -1);
  ins.created.assign(added.size(), 0);
  auto tree = base.index_grid ? std::make_shared<Int32Tree>(base.index_grid->tree())
                              : std::make_shared<Int32Tree>(-1);
  if (size_t(tree->activeVoxelCount()) != n) {
    // base's index grid does not number its vossels: number them first.
    VosselGeometry canonical = base;
    std::vector<int32_t> first = CanonicalizeVosselOrder(canonical);
    ins = InsertVossels(canonical, added, out);
    for (int32_t& k : first) k = ins.old_to_new[size_t(k)];
    ins.old_to_new = std::move(first);
    return ins;
  }
  {
    Int32Grid::Accessor acc(*tree);
    for (size_t i = 0; i < added.size(); ++i) {
      if (acc.isValueOn(added[i])) continue;
      acc.setValueOn(added[i], -1);
      ins.created[i] = 1;
    }
  }
  NumberInCanonicalOrder(*tree);
  tbb::parallel_for(tbb::blocked_range<size_t>(0, added.size(), kGrain),
                    [&](const tbb::blocked_range<size_t>& r) {
                      Int32Grid::ConstAccessor acc(*tree);
                      for (size_t i = r.begin(); i < r.end(); ++i) {
                        ins.added_to_new[i] = acc.getValue(added[i]);
                      }
                    });
  // The made vossels by their index p_r: base's keep their order, so the r-th made one has
  // p_r − r of base's before it, and between two made ones lies a run of base's.
  std::vector<std::pair<int32_t, size_t>> made;  // (index now, coordinate added)
  for (size_t i = 0; i < added.size(); ++i) {
    if (ins.created[i]) made.emplace_back(ins.added_to_new[i], i);
  }
  std::sort(made.begin(), made.end());
  const size_t m = n + made.size();
  ins.old_to_new.resize(n);
  tbb::parallel_for(size_t(0), made.size() + 1, [&](size_t r) {
    const size_t begin = r == 0 ? 0 : size_t(made[r - 1].first) - (r - 1);
    const size_t end = r == made.size() ? n : size_t(made[r].first) - r;
    for (size_t i = begin; i < end; ++i) ins.old_to_new[i] = int32_t(i + r);
  });
  // Each array in one pass: runs of base's values, the made vossels' between them.
  out->vossel_size_m = base.vossel_size_m;
  auto spread = [&](auto& into, const auto& from, const auto& fill, const auto& made_value) {
    into.clear();
    into.reserve(m);
    size_t at = 0;
    for (size_t r = 0; r < made.size(); ++r) {
      const size_t end = size_t(made[r].first) - r;
      AppendRun(into, from, at, end, fill);
      into.push_back(made_value(made[r].second));
      at = end;
    }
    AppendRun(into, from, at, n, fill);
  };
  auto as = [&](auto& into, const auto& from, const auto& fill) {
    spread(into, from, fill, [&](size_t) { return fill; });
  };
  const Eigen::Vector3f zero = Eigen::Vector3f::Zero();
  tbb::parallel_invoke(
      [&] { spread(out->coord, base.coord, Coord(), [&](size_t i) { return added[i]; }); },
      [&] { as(out->point_count, base.point_count, int32_t{0}); },
      [&] { as(out->centroid_m, base.centroid_m, zero); },
      [&] { as(out->normal, base.normal, zero); },
      [&] { as(out->covariance_m2, base.covariance_m2, std::array<float, 6>{}); },
      [&] { as(out->sums, base.sums, VosselSums{}); },
      [&] { as(out->frame, base.frame, VosselFrame{}); });
  out->index_grid = IndexGridOf(tree, base.vossel_size_m);
  return ins;
}

namespace {

// geometry.vdb and fused-<profile>.vdb without blosc (internal::VdbCompression): on the
// 12-scan corridor blosc made geometry files 4% and fused files 10% smaller, for 30% and 20%
// of their writing time (OpenVDB compresses each leaf twice).
constexpr internal::VdbCompression kGeometryCompression =
    internal::VdbCompression::kActiveMaskOnly;
constexpr internal::VdbCompression kFusedCompression = internal::VdbCompression::kActiveMaskOnly;

openvdb::MetaMap GeometryFileMeta(const VosselGeometry& geometry) {
  openvdb::MetaMap meta;
  meta.insertMeta("vasl_file", openvdb::StringMetadata("geometry"));
  meta.insertMeta("vossel_size_m", openvdb::DoubleMetadata(geometry.vossel_size_m));
  return meta;
}

openvdb::MetaMap FusedFileMeta(const FusedValues& fused) {
  openvdb::MetaMap meta;
  meta.insertMeta("vasl_file", openvdb::StringMetadata("fused"));
  meta.insertMeta("profile", openvdb::StringMetadata(fused.profile));
  return meta;
}

}  // namespace

absl::Status WriteGeometry(const VosselGeometry& geometry, const std::filesystem::path& path) {
  absl::StatusOr<openvdb::GridCPtrVec> grids = GeometryGrids(geometry, path.string());
  if (!grids.ok()) return grids.status();
  return internal::WriteVdbFile(path, *grids, GeometryFileMeta(geometry), kGeometryCompression);
}

namespace {

namespace pts = openvdb::points;
using pts::PointDataGrid;
using PointLeaf = pts::PointDataTree::LeafNodeType;
/// Attribute arrays of geometry and fused objects: the values as they are, no codec.
using internal::RawArray;
using internal::Tag;

/// The PointDataGrid of a geometry object: one point per vossel, in the vossel's voxel.
constexpr char kVosselPoints[] = "vossels";

/// Calls `fn(name, stride, array, at)` for every per-vossel attribute of a geometry object, in
/// file order: `array` is the geometry's vector that holds it (several attributes share the
/// sums' and the frames'), `at(element)` the pointer to its `stride` values in one element
/// (int32_t, float or double; const when `g` is).
template <typename G, typename Fn>
void ForEachVosselAttribute(G& g, Fn&& fn) {
  fn("count", 1, g.point_count, [](auto& c) { return &c; });
  fn("normal", 3, g.normal, [](auto& n) { return n.data(); });
  fn("centroid", 3, g.centroid_m, [](auto& c) { return c.data(); });
  fn("covariance", 6, g.covariance_m2, [](auto& c) { return c.data(); });
  fn("sum", 3, g.sums, [](auto& s) { return s.sum_m.data(); });
  fn("sum_xx", 6, g.sums, [](auto& s) { return s.sum_xx_m2.data(); });
  fn("view_sum", 3, g.sums, [](auto& s) { return s.view_sum.data(); });
  fn("frame_count", 1, g.frame, [](auto& f) { return &f.count; });
  fn("frame_centroid", 3, g.frame, [](auto& f) { return f.centroid_m.data(); });
  fn("frame_covariance", 6, g.frame, [](auto& f) { return f.covariance_m2.data(); });
  fn("frame_view", 3, g.frame, [](auto& f) { return f.view.data(); });
  fn("frame_normal", 3, g.frame, [](auto& f) { return f.normal.data(); });
}

/// Whether a geometry object keeps attribute `name`, held in `array`: every array the geometry
/// has, but the centroid and covariance where the sums they come from are kept (they are
/// derived again on reading, FrameOf, to the same bits).
template <typename Array>
bool Kept(const VosselGeometry& geometry, const char* name, const Array& array) {
  const bool derived = std::strcmp(name, "centroid") == 0 || std::strcmp(name, "covariance") == 0;
  return !array.empty() && !(derived && !geometry.sums.empty());
}

/// The value type `at` points to.
template <typename Array, typename At>
using ValueOf = std::remove_const_t<
    std::remove_pointer_t<std::invoke_result_t<At, typename Array::value_type&>>>;

/// A PointDataGrid `name` over the lattice of `index`: a point per vossel at its voxel's centre
/// (P uniform), in the leaves and voxel order of the index grid, so that each attribute of a
/// leaf is one contiguous run of vossels. `attributes(fn)` calls `fn(name, stride, Tag<T>{},
/// get)` for each attribute, `get(v, out)` writing vossel v's `stride` values of type T. One
/// pass over a vossel's values, against a grid, a topology copy and a scan of every leaf's 512
/// values per array for plain grids (GeometryGrids, FusedGrids: the files a user opens).
template <typename Attributes>
absl::StatusOr<openvdb::GridBase::Ptr> PointsOverVossels(const Int32Grid& index,
                                                         const char* name,
                                                         const std::string& where,
                                                         Attributes&& attributes) {
  try {
    // The prototype's arrays carry the strides (RECORDS-NOTES pitfall 3).
    auto descriptor = pts::AttributeSet::Descriptor::create(
        RawArray<openvdb::Vec3f>::attributeType());
    pts::AttributeSet prototype(descriptor, 1);
    attributes([&](const char* attribute, int stride, auto tag, auto&&) {
      using T = typename decltype(tag)::type;
      prototype.appendAttribute(attribute, RawArray<T>::attributeType(), stride);
    });
    const auto leaves = ConstLeavesInOrder(index.tree());
    std::vector<std::unique_ptr<PointLeaf>> points(leaves.size());
    {
      pts::AttributeArray::ScopedRegistryLock lock;  // one lock for every leaf (pitfall 5)
      tbb::parallel_for(tbb::blocked_range<size_t>(0, leaves.size(), 8),
                        [&](const tbb::blocked_range<size_t>& r) {
        std::vector<pts::PointDataTree::ValueType> offsets(PointLeaf::SIZE);
        for (size_t li = r.begin(); li < r.end(); ++li) {
          const Int32Leaf& leaf = *leaves[li];
          openvdb::Index32 end = 0;  // a voxel's value: the end of its points (pitfall 2)
          for (openvdb::Index o = 0; o < PointLeaf::SIZE; ++o) {
            offsets[o] = end += leaf.isValueOn(o) ? 1 : 0;
          }
          if (end == 0) continue;  // (an index leaf has vossels; a tree may keep an empty one)
          const size_t first = size_t(*leaf.cbeginValueOn());  // canonical: its vossels in a run
          auto set = std::make_unique<pts::AttributeSet>(prototype, end, &lock);
          size_t pos = 1;  // the attributes in the prototype's order, after P
          attributes([&](const char*, int stride, auto tag, auto&& get) {
            using T = typename decltype(tag)::type;
            auto& values = static_cast<RawArray<T>&>(*set->get(pos++));
            values.expand(/*fill=*/false);
            // Made for this leaf and not shared: its buffer is written in place.
            T* out = const_cast<T*>(values.constData());
            for (size_t v = first; v < first + end; ++v, out += stride) get(v, out);
          });
          auto point_leaf = std::make_unique<PointLeaf>(leaf.origin());
          point_leaf->replaceAttributeSet(set.release(), /*allowMismatchingDescriptors=*/true);
          // The offsets and the index leaf's mask, whole (setOffsets goes voxel by voxel).
          std::copy(offsets.begin(), offsets.end(), point_leaf->buffer().data());
          point_leaf->setValueMask(leaf.getValueMask());
          points[li] = std::move(point_leaf);
        }
      });
    }
    auto tree = std::make_shared<pts::PointDataTree>();
    for (auto& leaf : points) {
      if (leaf) tree->addLeaf(leaf.release());
    }
    auto grid = PointDataGrid::create(tree);
    grid->setTransform(index.transform().copy());
    grid->setName(name);
    return openvdb::GridBase::Ptr(grid);
  } catch (const std::exception& e) {
    return absl::InternalError(
        absl::StrCat("OpenVDB failed building the points of ", where, ": ", e.what()));
  }
}

/// Which attributes of `grid` (a PointDataGrid over a lattice: PointsOverVossels) `wanted(fn)`
/// finds, by name to position: `wanted` calls `fn(name, strides, Tag<T>{})` for each attribute
/// the reader knows, `strides` the strides it takes. One of another type or stride is
/// DATA_LOSS naming `path`. A grid without leaves has none.
template <typename Wanted>
absl::StatusOr<std::map<std::string, size_t>> FindPointAttributes(
    const PointDataGrid& grid, const std::filesystem::path& path, Wanted&& wanted) {
  std::map<std::string, size_t> present;
  auto leaf = grid.tree().cbeginLeaf();
  if (!leaf) return present;
  const pts::AttributeSet& set = leaf->attributeSet();
  absl::Status bad;
  wanted([&](const std::string& name, std::initializer_list<int> strides, auto tag) {
    using T = typename decltype(tag)::type;
    const size_t pos = set.find(name);
    if (pos == pts::AttributeSet::INVALID_POS || !bad.ok()) return;
    const int stride = int(set.getConst(pos)->stride());
    if (set.descriptor().type(pos) != RawArray<T>::attributeType() ||
        std::find(strides.begin(), strides.end(), stride) == strides.end()) {
      bad = absl::DataLossError(absl::StrCat(path.string(), ": the points \"", grid.getName(),
                                             "\" have attribute \"", name,
                                             "\" of another type or stride"));
      return;
    }
    present[name] = pos;
  });
  if (!bad.ok()) return bad;
  return present;
}

/// Copies the attributes of `grid` (a PointDataGrid over the lattice of `index`:
/// PointsOverVossels) into a reader's arrays: `attributes(fn)` calls `fn(name, Tag<T>{}, set)`
/// for each attribute the reader knows, the same ones in the same order on every call, `set(v,
/// in)` taking vossel v's values from `in`; those not in `present` (FindPointAttributes) are
/// skipped. The points must share the index grid's lattice leaf for leaf and voxel for voxel,
/// a point per vossel, and every leaf the same attributes; otherwise DATA_LOSS naming `path`.
template <typename Attributes>
absl::Status CopyPointAttributes(const PointDataGrid& grid, const Int32Grid& index,
                                 const std::filesystem::path& path,
                                 const std::map<std::string, size_t>& present,
                                 Attributes&& attributes) {
  std::vector<const PointLeaf*> leaves;
  leaves.reserve(grid.tree().leafCount());
  for (auto it = grid.tree().cbeginLeaf(); it; ++it) leaves.push_back(it.getLeaf());
  const auto mismatch = [&](const std::string& what) {
    return absl::DataLossError(
        absl::StrCat(path.string(), ": the points \"", grid.getName(), "\" ", what));
  };
  // (An index leaf without vossels has no point leaf: PointsOverVossels skips it.)
  std::vector<const Int32Leaf*> lattice_leaves;
  lattice_leaves.reserve(index.tree().leafCount());
  for (const Int32Leaf* leaf : ConstLeavesInOrder(index.tree())) {
    if (!leaf->isEmpty()) lattice_leaves.push_back(leaf);
  }
  if (leaves.size() != lattice_leaves.size()) {
    return mismatch("do not share the lattice of the index grid");
  }
  // Each attribute's position in the points' attribute sets, once for every leaf.
  std::vector<size_t> positions;
  attributes([&](const auto& name, auto, auto&&) {
    const auto it = present.find(name);
    positions.push_back(it == present.end() ? pts::AttributeSet::INVALID_POS : it->second);
  });
  FirstError error;
  tbb::parallel_for(tbb::blocked_range<size_t>(0, leaves.size(), 8),
                    [&](const tbb::blocked_range<size_t>& r) {
    for (size_t li = r.begin(); li < r.end() && !error.failed(); ++li) {
      const PointLeaf& leaf = *leaves[li];
      const Int32Leaf& lattice = *lattice_leaves[li];
      const size_t count = lattice.onVoxelCount();
      if (leaf.origin() != lattice.origin() || leaf.getValueMask() != lattice.getValueMask() ||
          leaf.getLastValue() != count || leaf.attributeSet().descriptor().map() !=
                                             leaves[0]->attributeSet().descriptor().map()) {
        error.Set(mismatch(absl::StrCat("differ from the index grid or between leaves at ",
                                        leaf.origin().asVec3i().str())));
        return;
      }
      const size_t first = size_t(*lattice.cbeginValueOn());
      size_t a = 0;
      attributes([&](const auto&, auto tag, auto&& set) {
        using T = typename decltype(tag)::type;
        const size_t pos = positions[a++];
        if (pos == pts::AttributeSet::INVALID_POS) return;
        const auto& values = static_cast<const RawArray<T>&>(*leaf.attributeSet().getConst(pos));
        values.loadData();  // (a delayed load's)
        // A uniform array (every vossel alike) holds one vossel's values.
        const size_t step = values.isUniform() ? 0 : values.stride();
        const T* in = values.constData();
        for (size_t v = first; v < first + count; ++v, in += step) set(v, in);
      });
    }
  });
  return error.status();
}

/// A geometry object's per-vossel arrays as its vossel points (PointsOverVossels).
absl::StatusOr<openvdb::GridBase::Ptr> VosselPoints(const VosselGeometry& geometry,
                                                    const std::string& where) {
  return PointsOverVossels(
      *geometry.index_grid, kVosselPoints, where, [&](auto&& fn) {
        ForEachVosselAttribute(geometry, [&](const char* name, int stride, const auto& array,
                                             auto at) {
          using T = ValueOf<std::decay_t<decltype(array)>, decltype(at)>;
          if (!Kept(geometry, name, array)) return;
          fn(name, stride, Tag<T>{},
             [&](size_t v, T* out) { std::copy_n(at(array[v]), stride, out); });
        });
      });
}

/// Reads the attributes of a geometry object's vossel points (VosselPoints) into `g`, which
/// holds the object's lattice (LatticeOf). An attribute of a group (the sums, the frames)
/// without the rest of its group is DATA_LOSS, as CopyPointAttributes' mismatches are.
absl::Status ReadVosselPoints(const PointDataGrid& grid, const std::filesystem::path& path,
                              VosselGeometry& g) {
  absl::StatusOr<std::map<std::string, size_t>> present =
      FindPointAttributes(grid, path, [&](auto&& fn) {
        ForEachVosselAttribute(g, [&](const char* name, int stride, auto& array, auto at) {
          fn(name, {stride}, Tag<ValueOf<std::decay_t<decltype(array)>, decltype(at)>>{});
        });
      });
  if (!present.ok()) return present.status();
  for (const auto& group : {std::vector<const char*>{"sum", "sum_xx", "view_sum"},
                            {"frame_count", "frame_centroid", "frame_covariance", "frame_view",
                             "frame_normal"}}) {
    const size_t has = std::count_if(group.begin(), group.end(),
                                     [&](const char* a) { return present->count(a) > 0; });
    if (has != 0 && has != group.size()) {
      return absl::DataLossError(absl::StrCat(path.string(), ": the vossel points have some of ",
                                              "the attributes of \"", group[0],
                                              "\" and not the others"));
    }
  }
  ForEachVosselAttribute(g, [&](const char* name, int, auto& array, auto) {
    if (present->count(name) && array.size() != g.size()) array.resize(g.size());
  });
  return CopyPointAttributes(grid, *g.index_grid, path, *present, [&](auto&& fn) {
    ForEachVosselAttribute(g, [&](const char* name, int stride, auto& array, auto at) {
      using T = ValueOf<std::decay_t<decltype(array)>, decltype(at)>;
      fn(name, Tag<T>{}, [&](size_t v, const T* in) { std::copy_n(in, stride, at(array[v])); });
    });
  });
}

/// Checks that `geometry` can be written: an index grid in canonical order over its vossels,
/// and every array empty or one entry a vossel. Returns the index grid's copy the file holds
/// ("index": it shares the tree).
absl::StatusOr<openvdb::GridBase::Ptr> CheckedIndex(const VosselGeometry& geometry,
                                                    const std::string& where) {
  internal::EnsureOpenVdbInitialized();
  if (!geometry.index_grid) {
    return absl::InvalidArgumentError(
        "WriteGeometry: the geometry has no index grid; call CanonicalizeVosselOrder first");
  }
  absl::StatusOr<size_t> n = internal::CheckCanonicalOrder(*geometry.index_grid, where);
  if (!n.ok()) return n.status();
  if (*n != geometry.coord.size()) {
    return absl::InvalidArgumentError(absl::StrCat("WriteGeometry: the index grid has ", *n,
                                                   " vossels but coord has ",
                                                   geometry.coord.size()));
  }
  for (absl::Status s : {CheckArraySize(geometry.point_count.size(), *n, 1, "point_count"),
                         CheckArraySize(geometry.centroid_m.size(), *n, 1, "centroid_m"),
                         CheckArraySize(geometry.normal.size(), *n, 1, "normal"),
                         CheckArraySize(geometry.covariance_m2.size(), *n, 1, "covariance_m2"),
                         CheckArraySize(geometry.sums.size(), *n, 1, "sums"),
                         CheckArraySize(geometry.frame.size(), *n, 1, "frame")}) {
    if (!s.ok()) return s;
  }
  openvdb::GridBase::Ptr index_copy = geometry.index_grid->copyGrid();  // own name and meta
  index_copy->setName("index");
  index_copy->setGridClass(openvdb::GRID_UNKNOWN);
  return index_copy;
}

}  // namespace

absl::StatusOr<std::string> EncodeGeometry(const VosselGeometry& geometry) {
  constexpr char kWhere[] = "geometry object";
  absl::StatusOr<openvdb::GridBase::Ptr> index = CheckedIndex(geometry, kWhere);
  if (!index.ok()) return index.status();
  absl::StatusOr<openvdb::GridBase::Ptr> vossels = VosselPoints(geometry, kWhere);
  if (!vossels.ok()) return vossels.status();
  return internal::EncodeVdbFile({*index, *vossels}, GeometryFileMeta(geometry),
                                 kGeometryCompression, kWhere, internal::VdbGridStats::kSkip);
}

absl::StatusOr<openvdb::GridCPtrVec> GeometryGrids(const VosselGeometry& geometry,
                                                   const std::string& where) {
  absl::StatusOr<openvdb::GridBase::Ptr> index_copy = CheckedIndex(geometry, where);
  if (!index_copy.ok()) return index_copy.status();
  const Int32Grid& index = *geometry.index_grid;
  openvdb::GridCPtrVec grids{*index_copy};
  using openvdb::Vec3f;
  using openvdb::Vec3SGrid;
  if (!geometry.point_count.empty()) {
    grids.push_back(GridOverVossels<Int32Grid>(
        index, "count", [&](int32_t v) { return geometry.point_count[v]; }));
  }
  if (!geometry.centroid_m.empty()) {
    grids.push_back(GridOverVossels<Vec3SGrid>(index, "centroid", [&](int32_t v) {
      const Eigen::Vector3f& c = geometry.centroid_m[v];
      return Vec3f(c.x(), c.y(), c.z());
    }));
  }
  if (!geometry.normal.empty()) {
    grids.push_back(GridOverVossels<Vec3SGrid>(index, "normal", [&](int32_t v) {
      const Eigen::Vector3f& c = geometry.normal[v];
      return Vec3f(c.x(), c.y(), c.z());
    }));
  }
  if (!geometry.covariance_m2.empty()) {
    PushCovarianceGrids(grids, index, "covariance",
                        [&](int32_t v) -> const std::array<float, 6>& {
                          return geometry.covariance_m2[v];
                        });
  }
  if (!geometry.sums.empty()) {
    // The exact running sums (double) that make merging scans exact (§1, records.h).
    using openvdb::Vec3d;
    using openvdb::Vec3DGrid;
    grids.push_back(GridOverVossels<Vec3DGrid>(index, "sum", [&](int32_t v) {
      const Eigen::Vector3d& c = geometry.sums[v].sum_m;
      return Vec3d(c.x(), c.y(), c.z());
    }));
    grids.push_back(GridOverVossels<Vec3DGrid>(index, "sum_xx_diag", [&](int32_t v) {
      const auto& c = geometry.sums[v].sum_xx_m2;
      return Vec3d(c[0], c[3], c[5]);
    }));
    grids.push_back(GridOverVossels<Vec3DGrid>(index, "sum_xx_off", [&](int32_t v) {
      const auto& c = geometry.sums[v].sum_xx_m2;
      return Vec3d(c[1], c[2], c[4]);
    }));
    grids.push_back(GridOverVossels<Vec3DGrid>(index, "view_sum", [&](int32_t v) {
      const Eigen::Vector3d& c = geometry.sums[v].view_sum;
      return Vec3d(c.x(), c.y(), c.z());
    }));
  }
  if (!geometry.frame.empty()) {
    // The record frames (records.h VosselFrame): float, never merged, so stored as derived.
    auto vec3 = [](const Eigen::Vector3f& c) { return Vec3f(c.x(), c.y(), c.z()); };
    grids.push_back(GridOverVossels<Int32Grid>(
        index, "frame_count", [&](int32_t v) { return geometry.frame[v].count; }));
    grids.push_back(GridOverVossels<Vec3SGrid>(
        index, "frame_centroid", [&](int32_t v) { return vec3(geometry.frame[v].centroid_m); }));
    PushCovarianceGrids(grids, index, "frame_covariance",
                        [&](int32_t v) -> const std::array<float, 6>& {
                          return geometry.frame[v].covariance_m2;
                        });
    grids.push_back(GridOverVossels<Vec3SGrid>(
        index, "frame_view", [&](int32_t v) { return vec3(geometry.frame[v].view); }));
    grids.push_back(GridOverVossels<Vec3SGrid>(
        index, "frame_normal", [&](int32_t v) { return vec3(geometry.frame[v].normal); }));
  }
  return grids;
}

namespace {

/// The lattice of a geometry file's contents: its index grid, checked, and the coordinates of
/// its vossels in vossel order.
absl::StatusOr<VosselGeometry> LatticeOf(const internal::VdbFileContents& contents,
                                         const std::filesystem::path& path) {
  Int32Grid::Ptr index = GridAs<Int32Grid>(contents, "index");
  if (!index) {
    return absl::DataLossError(
        absl::StrCat(path.string(), " has no Int32 grid named \"index\"; not a geometry file"));
  }
  absl::StatusOr<size_t> n = internal::CheckCanonicalOrder(*index, path.string());
  if (!n.ok()) return absl::DataLossError(n.status().message());
  VosselGeometry g;
  g.vossel_size_m = index->transform().voxelSize()[0];
  g.index_grid = index;
  g.coord.resize(*n);
  const auto leaves = ConstLeavesInOrder(index->tree());
  tbb::parallel_for(tbb::blocked_range<size_t>(0, leaves.size(), 16),
                    [&](const tbb::blocked_range<size_t>& r) {
                      for (size_t i = r.begin(); i < r.end(); ++i) {
                        for (auto it = leaves[i]->cbeginValueOn(); it; ++it) {
                          g.coord[*it] = it.getCoord();
                        }
                      }
                    });
  return g;
}

}  // namespace

absl::StatusOr<VosselGeometry> ReadLattice(const std::filesystem::path& path) {
  absl::StatusOr<internal::VdbFileContents> contents = internal::ReadVdbGrids(path, {"index"});
  if (!contents.ok()) return contents.status();
  return LatticeOf(*contents, path);
}

namespace {

/// Reads the arrays of a geometry file kept as plain grids (GeometryGrids; the geometry objects
/// of stores written before VosselPoints) into `g`, which holds the file's lattice.
absl::Status ReadGeometryGrids(const internal::VdbFileContents& contents,
                               const std::filesystem::path& path, VosselGeometry& g) {
  const Int32Grid::Ptr index = g.index_grid;
  const size_t n = g.size();
  // Companion grids are read by active vossel, so any topology that is a subset works.
  if (auto count = GridAs<Int32Grid>(contents, "count")) {
    g.point_count.assign(n, 0);
    absl::Status s = ForEachActiveVossel(*index, *count, path,
                                         [&](int32_t v, int32_t c) { g.point_count[v] = c; });
    if (!s.ok()) return s;
  }
  auto read_vec3 = [&](const char* name, std::vector<Eigen::Vector3f>& out) -> absl::Status {
    auto grid = GridAs<openvdb::Vec3SGrid>(contents, name);
    if (!grid) return absl::OkStatus();
    out.assign(n, Eigen::Vector3f::Zero());
    return ForEachActiveVossel(*index, *grid, path, [&](int32_t v, const openvdb::Vec3f& c) {
      out[v] = Eigen::Vector3f(c.x(), c.y(), c.z());
    });
  };
  if (absl::Status s = read_vec3("centroid", g.centroid_m); !s.ok()) return s;
  if (absl::Status s = read_vec3("normal", g.normal); !s.ok()) return s;
  std::vector<Eigen::Vector3f> diag, off;
  if (absl::Status s = read_vec3("covariance_diag", diag); !s.ok()) return s;
  if (absl::Status s = read_vec3("covariance_off", off); !s.ok()) return s;
  if (!diag.empty() || !off.empty()) {
    diag.resize(n, Eigen::Vector3f::Zero());
    off.resize(n, Eigen::Vector3f::Zero());
    g.covariance_m2.resize(n);
    for (size_t v = 0; v < n; ++v) g.covariance_m2[v] = CovarianceFrom(diag[v], off[v]);
  }
  if (GridAs<openvdb::Vec3DGrid>(contents, "sum")) {
    g.sums.assign(n, VosselSums{});
    auto read_vec3d = [&](const char* name, auto&& set) -> absl::Status {
      auto grid = GridAs<openvdb::Vec3DGrid>(contents, name);
      if (!grid) {
        return absl::DataLossError(absl::StrCat(path.string(), " has \"sum\" but no Vec3d grid \"",
                                                name, "\""));
      }
      return ForEachActiveVossel(*index, *grid, path, set);
    };
    for (absl::Status s : {
             read_vec3d("sum", [&](int32_t v, const openvdb::Vec3d& c) {
               g.sums[v].sum_m = Eigen::Vector3d(c.x(), c.y(), c.z());
             }),
             read_vec3d("sum_xx_diag", [&](int32_t v, const openvdb::Vec3d& c) {
               auto& s = g.sums[v].sum_xx_m2;
               s[0] = c.x(), s[3] = c.y(), s[5] = c.z();
             }),
             read_vec3d("sum_xx_off", [&](int32_t v, const openvdb::Vec3d& c) {
               auto& s = g.sums[v].sum_xx_m2;
               s[1] = c.x(), s[2] = c.y(), s[4] = c.z();
             }),
             read_vec3d("view_sum", [&](int32_t v, const openvdb::Vec3d& c) {
               g.sums[v].view_sum = Eigen::Vector3d(c.x(), c.y(), c.z());
             })}) {
      if (!s.ok()) return s;
    }
  }
  if (auto count = GridAs<Int32Grid>(contents, "frame_count")) {
    g.frame.assign(n, VosselFrame{});
    if (absl::Status s = ForEachActiveVossel(*index, *count, path,
                                             [&](int32_t v, int32_t c) { g.frame[v].count = c; });
        !s.ok()) {
      return s;
    }
    std::vector<Eigen::Vector3f> centroid, cov_diag, cov_off, view, normal;
    for (auto [name, out] : {std::pair<const char*, std::vector<Eigen::Vector3f>*>{
                                 "frame_centroid", &centroid},
                             {"frame_covariance_diag", &cov_diag},
                             {"frame_covariance_off", &cov_off},
                             {"frame_view", &view},
                             {"frame_normal", &normal}}) {
      if (!GridAs<openvdb::Vec3SGrid>(contents, name)) {
        return absl::DataLossError(absl::StrCat(
            path.string(), " has \"frame_count\" but no Vec3s grid \"", name, "\""));
      }
      if (absl::Status s = read_vec3(name, *out); !s.ok()) return s;
    }
    for (size_t v = 0; v < n; ++v) {
      VosselFrame& f = g.frame[v];
      f.centroid_m = centroid[v];
      f.covariance_m2 = CovarianceFrom(cov_diag[v], cov_off[v]);
      f.view = view[v];
      f.normal = normal[v];
    }
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<VosselGeometry> ReadGeometry(const std::filesystem::path& path) {
  absl::StatusOr<internal::VdbFileContents> contents = internal::ReadVdbFile(path);
  if (!contents.ok()) return contents.status();
  absl::StatusOr<VosselGeometry> lattice = LatticeOf(*contents, path);
  if (!lattice.ok()) return lattice.status();
  VosselGeometry& g = *lattice;
  const PointDataGrid::Ptr vossels = GridAs<PointDataGrid>(*contents, kVosselPoints);
  const absl::Status read = vossels ? ReadVosselPoints(*vossels, path, g)
                                    : ReadGeometryGrids(*contents, path, g);
  if (!read.ok()) return read;
  const size_t n = g.size();
  if (!g.sums.empty() && g.centroid_m.empty() && g.covariance_m2.empty() &&
      g.point_count.size() == n) {
    // Written with the sums alone (a geometry object): what they give, derived.
    DeriveCentroidAndCovariance(g);
  }
  if (g.frame.empty() && !g.sums.empty() && g.point_count.size() == n &&
      g.centroid_m.size() == n && g.normal.size() == n && g.covariance_m2.size() == n) {
    // Written before record frames: each vossel's surface becomes its frame (the records
    // stored with it were evaluated on that surface).
    g.frame.resize(n);
    for (size_t v = 0; v < n; ++v) {
      g.frame[v] = {g.point_count[v], g.centroid_m[v], g.covariance_m2[v],
                    g.sums[v].view_sum.cast<float>(), g.normal[v]};
    }
  }
  return lattice;
}

absl::Status WriteFused(const VosselGeometry& geometry, const FusedValues& fused,
                        const std::filesystem::path& path) {
  absl::StatusOr<openvdb::GridCPtrVec> grids = FusedGrids(geometry, fused);
  if (!grids.ok()) return grids.status();
  return internal::WriteVdbFile(path, *grids, FusedFileMeta(fused), kFusedCompression);
}

namespace {

/// The PointDataGrid of a fused object: one point per vossel, in the vossel's voxel, with per
/// modality "<modality>_value", "_weight" and "_uncertainty" (an attribute's name takes no '.',
/// which the plain grids' "<modality>.value" have).
constexpr char kFusedPoints[] = "fused";

/// Checks that `fused` can be written over `geometry`: an index grid, and per modality 1 or 3
/// channels and arrays of one entry a vossel.
absl::Status CheckFused(const VosselGeometry& geometry, const FusedValues& fused) {
  internal::EnsureOpenVdbInitialized();
  if (!geometry.index_grid) {
    return absl::InvalidArgumentError("WriteFused: the geometry has no index grid");
  }
  const size_t n = geometry.size();
  for (const auto& [modality, fm] : fused.by_modality) {
    const std::string name = ModalityName(modality);
    if (fm.channels != 1 && fm.channels != 3) {
      return absl::InvalidArgumentError(absl::StrCat("WriteFused: modality ", name, " has ",
                                                     fm.channels, " channels; expected 1 or 3"));
    }
    if (fm.value.size() != n * fm.channels || fm.weight.size() != n ||
        fm.uncertainty.size() != n) {
      return absl::InvalidArgumentError(absl::StrCat(
          "WriteFused: modality ", name, " arrays do not match the ", n,
          " vossels (value ", fm.value.size(), ", weight ", fm.weight.size(), ", uncertainty ",
          fm.uncertainty.size(), ")"));
    }
  }
  return absl::OkStatus();
}

/// The attribute names of `modality` in a fused object: value, weight, uncertainty (an
/// OpenVDB attribute name takes no '.').
std::array<std::string, 3> FusedAttributeNames(Modality modality) {
  const std::string name = ModalityName(modality);
  return {name + "_value", name + "_weight", name + "_uncertainty"};
}
/// Those of each modality of `fused`, in its order.
std::vector<std::array<std::string, 3>> FusedAttributeNames(const FusedValues& fused) {
  std::vector<std::array<std::string, 3>> names;
  for (const auto& [modality, fm] : fused.by_modality) {
    names.push_back(FusedAttributeNames(modality));
  }
  return names;
}

/// Reads a fused object's points (EncodeFused) into `fused`, over the lattice of `geometry`.
/// A modality's value without its weight and uncertainty is DATA_LOSS, as CopyPointAttributes'
/// mismatches are.
absl::Status ReadFusedPoints(const PointDataGrid& grid, const VosselGeometry& geometry,
                             const std::filesystem::path& path, FusedValues& fused) {
  absl::StatusOr<std::map<std::string, size_t>> present =
      FindPointAttributes(grid, path, [&](auto&& fn) {
        for (int m = 0; m < kModalityCount; ++m) {
          const std::array<std::string, 3> name = FusedAttributeNames(static_cast<Modality>(m));
          fn(name[0], {1, 3}, Tag<float>{});
          fn(name[1], {1}, Tag<float>{});
          fn(name[2], {1}, Tag<float>{});
        }
      });
  if (!present.ok()) return present.status();
  const size_t n = geometry.size();
  if (!grid.tree().cbeginLeaf()) {  // no vossels: the modalities from the grid's metadata
    if (n != 0) {
      return absl::DataLossError(absl::StrCat(path.string(), ": the points \"", kFusedPoints,
                                              "\" have none of the geometry's ", n, " vossels"));
    }
    const auto meta = grid.getMetadata<openvdb::StringMetadata>("modalities");
    for (int m = 0; meta && m < kModalityCount; ++m) {
      const Modality modality = static_cast<Modality>(m);
      for (absl::string_view item : absl::StrSplit(meta->value(), ',', absl::SkipEmpty())) {
        const std::pair<absl::string_view, absl::string_view> kv = absl::StrSplit(item, ':');
        int channels = 0;
        if (kv.first == ModalityName(modality) && absl::SimpleAtoi(kv.second, &channels) &&
            (channels == 1 || channels == 3)) {
          fused.by_modality[modality].channels = channels;
        }
      }
    }
    return absl::OkStatus();
  }
  for (int m = 0; m < kModalityCount; ++m) {
    const Modality modality = static_cast<Modality>(m);
    const std::array<std::string, 3> name = FusedAttributeNames(modality);
    const auto value = present->find(name[0]);
    const size_t has =
        (value != present->end()) + present->count(name[1]) + present->count(name[2]);
    if (has == 0) continue;
    if (has != 3) {
      return absl::DataLossError(absl::StrCat(path.string(), ": modality ",
                                              ModalityName(modality),
                                              " lacks its value, weight or uncertainty"));
    }
    FusedModality& fm = fused.by_modality[modality];
    fm.channels = int(grid.tree().cbeginLeaf()->attributeSet().getConst(value->second)->stride());
    fm.value.assign(n * size_t(fm.channels), 0.0f);
    fm.weight.assign(n, 0.0f);
    fm.uncertainty.assign(n, 0.0f);
  }
  const std::vector<std::array<std::string, 3>> names = FusedAttributeNames(fused);
  return CopyPointAttributes(grid, *geometry.index_grid, path, *present, [&](auto&& fn) {
    size_t m = 0;
    for (auto& [modality, fm] : fused.by_modality) {
      const std::array<std::string, 3>& name = names[m++];
      const size_t c = size_t(fm.channels);
      FusedModality* f = &fm;
      fn(name[0], Tag<float>{},
         [f, c](size_t v, const float* in) { std::copy_n(in, c, &f->value[v * c]); });
      fn(name[1], Tag<float>{}, [f](size_t v, const float* in) { f->weight[v] = *in; });
      fn(name[2], Tag<float>{}, [f](size_t v, const float* in) { f->uncertainty[v] = *in; });
    }
  });
}

}  // namespace

absl::StatusOr<std::string> EncodeFused(const VosselGeometry& geometry,
                                        const FusedValues& fused) {
  constexpr char kWhere[] = "fused object";
  if (absl::Status s = CheckFused(geometry, fused); !s.ok()) return s;
  // A vossel whose weight is not > 0 has no fused value: zeros, as a plain grid's inactive
  // voxels read (FusedGrids, ReadFused).
  const std::vector<std::array<std::string, 3>> names = FusedAttributeNames(fused);
  absl::StatusOr<openvdb::GridBase::Ptr> points = PointsOverVossels(
      *geometry.index_grid, kFusedPoints, kWhere, [&](auto&& fn) {
        size_t m = 0;
        for (const auto& [modality, fm] : fused.by_modality) {
          const std::array<std::string, 3>& name = names[m++];
          const size_t c = size_t(fm.channels);
          const FusedModality* f = &fm;
          fn(name[0].c_str(), int(c), Tag<float>{}, [f, c](size_t v, float* out) {
            const bool weighed = f->weight[v] > 0.0f;
            for (size_t i = 0; i < c; ++i) out[i] = weighed ? f->value[v * c + i] : 0.0f;
          });
          fn(name[1].c_str(), 1, Tag<float>{}, [f](size_t v, float* out) {
            *out = f->weight[v] > 0.0f ? f->weight[v] : 0.0f;
          });
          fn(name[2].c_str(), 1, Tag<float>{}, [f](size_t v, float* out) {
            *out = f->weight[v] > 0.0f ? f->uncertainty[v] : 0.0f;
          });
        }
      });
  if (!points.ok()) return points.status();
  // The modalities and their channels, for a reader of an object without vossels (no leaf
  // holds the attributes then).
  std::string modalities;
  for (const auto& [modality, fm] : fused.by_modality) {
    absl::StrAppend(&modalities, modalities.empty() ? "" : ",", ModalityName(modality), ":",
                    fm.channels);
  }
  (*points)->insertMeta("modalities", openvdb::StringMetadata(modalities));
  return internal::EncodeVdbFile({*points}, FusedFileMeta(fused), kFusedCompression, kWhere,
                                 internal::VdbGridStats::kSkip);
}

absl::StatusOr<openvdb::GridCPtrVec> FusedGrids(const VosselGeometry& geometry,
                                                const FusedValues& fused) {
  if (absl::Status s = CheckFused(geometry, fused); !s.ok()) return s;
  const Int32Grid& index = *geometry.index_grid;
  openvdb::GridCPtrVec grids;
  for (const auto& [modality, fm] : fused.by_modality) {
    const std::string name = ModalityName(modality);
    // Only vossels with weight > 0 stay active; fully inactive leaves are pruned.
    auto keep = [&fm](int32_t v) { return fm.weight[v] > 0.0f; };
    auto finish = [&](auto grid) {
      openvdb::tools::pruneInactive(grid->tree());  // only all-inactive leaves become tiles
      grid->insertMeta("profile", openvdb::StringMetadata(fused.profile));
      grid->insertMeta("modality", openvdb::Int32Metadata(static_cast<int>(modality)));
      grids.push_back(grid);
    };
    if (fm.channels == 3) {
      finish(GridOverVossels<openvdb::Vec3SGrid>(index, name + ".value", [&](int32_t v) {
        return openvdb::Vec3f(fm.value[3 * v], fm.value[3 * v + 1], fm.value[3 * v + 2]);
      }, keep));
    } else {
      finish(GridOverVossels<openvdb::FloatGrid>(index, name + ".value",
                                                 [&](int32_t v) { return fm.value[v]; }, keep));
    }
    finish(GridOverVossels<openvdb::FloatGrid>(index, name + ".weight",
                                               [&](int32_t v) { return fm.weight[v]; }, keep));
    finish(GridOverVossels<openvdb::FloatGrid>(index, name + ".uncertainty",
                                               [&](int32_t v) { return fm.uncertainty[v]; }, keep));
  }
  return grids;
}

absl::StatusOr<FusedValues> ReadFused(const VosselGeometry& geometry,
                                      const std::filesystem::path& path) {
  if (!geometry.index_grid) {
    return absl::InvalidArgumentError("ReadFused: the geometry has no index grid");
  }
  absl::StatusOr<internal::VdbFileContents> contents = internal::ReadVdbFile(path);
  if (!contents.ok()) return contents.status();
  const Int32Grid& index = *geometry.index_grid;
  const size_t n = geometry.size();
  FusedValues fused;
  if (auto p = contents->meta->getMetadata<openvdb::StringMetadata>("profile")) {
    fused.profile = p->value();
  }
  if (const PointDataGrid::Ptr points = GridAs<PointDataGrid>(*contents, kFusedPoints)) {
    if (absl::Status s = ReadFusedPoints(*points, geometry, path, fused); !s.ok()) return s;
    return fused;
  }
  for (int m = 0; m < kModalityCount; ++m) {
    const Modality modality = static_cast<Modality>(m);
    const std::string name = ModalityName(modality);
    openvdb::GridBase::Ptr value_base = internal::FindGrid(*contents, name + ".value");
    if (!value_base) continue;
    FusedModality fm;
    auto weight = GridAs<openvdb::FloatGrid>(*contents, name + ".weight");
    auto uncertainty = GridAs<openvdb::FloatGrid>(*contents, name + ".uncertainty");
    if (!weight || !uncertainty) {
      return absl::DataLossError(absl::StrCat(path.string(), ": modality ", name,
                                              " lacks its float weight or uncertainty grid"));
    }
    fm.weight.assign(n, 0.0f);
    fm.uncertainty.assign(n, 0.0f);
    absl::Status s;
    if (auto v3 = openvdb::GridBase::grid<openvdb::Vec3SGrid>(value_base)) {
      fm.channels = 3;
      fm.value.assign(3 * n, 0.0f);
      s = ForEachActiveVossel(index, *v3, path, [&](int32_t v, const openvdb::Vec3f& c) {
        fm.value[3 * v] = c.x();
        fm.value[3 * v + 1] = c.y();
        fm.value[3 * v + 2] = c.z();
      });
    } else if (auto v1 = openvdb::GridBase::grid<openvdb::FloatGrid>(value_base)) {
      fm.channels = 1;
      fm.value.assign(n, 0.0f);
      s = ForEachActiveVossel(index, *v1, path, [&](int32_t v, float c) { fm.value[v] = c; });
    } else {
      return absl::DataLossError(absl::StrCat(path.string(), ": grid ", name,
                                              ".value is neither Vec3s nor float"));
    }
    if (!s.ok()) return s;
    s = ForEachActiveVossel(index, *weight, path, [&](int32_t v, float w) { fm.weight[v] = w; });
    if (!s.ok()) return s;
    s = ForEachActiveVossel(index, *uncertainty, path,
                            [&](int32_t v, float u) { fm.uncertainty[v] = u; });
    if (!s.ok()) return s;
    fused.by_modality.emplace(modality, std::move(fm));
  }
  return fused;
}

}  // namespace vasl::records

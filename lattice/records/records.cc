#include "lattice/records/records.h"

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <numeric>
#include <tuple>
#include <type_traits>
#include <utility>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/task_group.h>

namespace vasl::records {

const char* ModalityName(Modality m) {
  switch (m) {
    case Modality::kLidar: return "lidar";
    case Modality::kRgb: return "rgb";
    case Modality::kIr: return "ir";
    case Modality::kRadar: return "radar";
    case Modality::kDerived: return "derived";
    default: return "unspecified";
  }
}

VosselFrame FrameOf(const openvdb::Coord& k, int32_t count, const VosselSums& s, double h) {
  VosselFrame f;
  f.count = count;
  const double n = std::max(1, count);
  const Eigen::Vector3d mu = s.sum_m / n;
  f.centroid_m = (h * Eigen::Vector3d(k.x(), k.y(), k.z()) + mu).cast<float>();
  const auto& q = s.sum_xx_m2;
  f.covariance_m2 = {float(q[0] / n - mu.x() * mu.x()), float(q[1] / n - mu.x() * mu.y()),
                     float(q[2] / n - mu.x() * mu.z()), float(q[3] / n - mu.y() * mu.y()),
                     float(q[4] / n - mu.y() * mu.z()), float(q[5] / n - mu.z() * mu.z())};
  f.view = s.view_sum.cast<float>();
  return f;
}

void DeriveCentroidAndCovariance(VosselGeometry& g, const std::vector<uint8_t>* only) {
  const size_t nv = g.size();
  const double h = g.vossel_size_m;
  g.centroid_m.resize(nv);
  g.covariance_m2.resize(nv);
  tbb::parallel_for(tbb::blocked_range<size_t>(0, nv, 4096), [&](const tbb::blocked_range<size_t>& r) {
    for (size_t v = r.begin(); v != r.end(); ++v) {
      if (only != nullptr && !(*only)[v]) continue;
      const VosselFrame all = FrameOf(g.coord[v], g.point_count[v], g.sums[v], h);
      g.centroid_m[v] = all.centroid_m;
      g.covariance_m2[v] = all.covariance_m2;
    }
  });
}

namespace {
// Applies `fn(stride, s.member...)` to every array of the RecordSets `s`, so that the
// operations below list the fields once.
template <typename Fn, typename... Sets>
void ForEachArrayOf(Fn&& fn, Sets&... s) {
  // Strides as types: a copy of one record's values (std::copy_n of a constant count) is then
  // a few moves, not a call to memmove per record.
  using One = std::integral_constant<int, 1>;
  fn(One{}, s.vossel...);
  fn(One{}, s.scan...);
  fn(One{}, s.modality...);
  fn(std::integral_constant<int, kValueChannels>{}, s.value...);
  fn(One{}, s.range_m...);
  fn(One{}, s.cos_inc...);
  fn(One{}, s.foot_major_m...);
  fn(One{}, s.foot_minor_m...);
  fn(std::integral_constant<int, 2>{}, s.uv_px...);
  fn(One{}, s.vis...);
  fn(std::integral_constant<int, kConfidenceCount>{}, s.conf...);
  fn(One{}, s.flags...);
  fn(One{}, s.batch...);
}
// `fn(a.member, b.member, stride)` for every array of two RecordSets (pass the same set twice
// for single-set operations).
template <typename A, typename B, typename Fn>
void ForEachArray(A& a, B& b, Fn&& fn) {
  ForEachArrayOf([&fn](auto stride, auto& x, auto& y) { fn(x, y, stride); }, a, b);
}
}  // namespace

void RecordSet::Reserve(size_t n) {
  ForEachArray(*this, *this, [n](auto& a, auto&, int stride) { a.reserve(n * stride); });
}

void RecordSet::Resize(size_t n) {
  ForEachArray(*this, *this, [n](auto& a, auto&, int stride) { a.resize(n * stride); });
}

void RecordSet::Append(const RecordSet& other) {
  ForEachArray(*this, other, [](auto& dst, const auto& src, int) {
    dst.insert(dst.end(), src.begin(), src.end());
  });
}

void RecordSet::SortByVossel() {
  const size_t n = size();
  auto key_less = [this](size_t a, size_t b) {
    return std::tie(vossel[a], scan[a], modality[a]) < std::tie(vossel[b], scan[b], modality[b]);
  };
  // A stable sort orders by (key, position). The longest run already in order (a change's
  // records carried over, say) is kept as it is, the rest sorted, and the two merged.
  size_t run_begin = 0, run_end = std::min<size_t>(n, 1);
  for (size_t begin = 0, i = 1; i <= n; ++i) {
    if (i < n && !key_less(i, i - 1)) continue;
    if (i - begin > run_end - run_begin) {
      run_begin = begin;
      run_end = i;
    }
    begin = i;
  }
  if (run_begin == 0 && run_end == n) return;  // in order already
  std::vector<uint32_t> rest;
  rest.reserve(n - (run_end - run_begin));
  for (size_t i = 0; i < n; ++i) {
    if (i < run_begin || i >= run_end) rest.push_back(uint32_t(i));
  }
  std::stable_sort(rest.begin(), rest.end(), key_less);
  if (run_begin > 0) {  // merged into new arrays
    std::vector<uint32_t> run(run_end - run_begin), order(n);
    std::iota(run.begin(), run.end(), uint32_t(run_begin));
    std::merge(run.begin(), run.end(), rest.begin(), rest.end(), order.begin(),
               [&key_less](uint32_t a, uint32_t b) {
                 return key_less(a, b) || (!key_less(b, a) && a < b);
               });
    *this = Select(std::vector<size_t>(order.begin(), order.end()));
    return;
  }
  // The run is a prefix (records appended to sorted ones): merged in place from the back. Each
  // position from the last down takes the greater of the run's last unplaced record and the
  // rest's (the rest's on a tie: it came later); a run record moves only toward the end, so it
  // is read before its position is written. The run's records before the first insertion stay.
  std::vector<size_t> from(n);
  size_t i = run_end, j = rest.size(), k = n;
  while (j > 0) {
    --k;
    if (i > 0 && key_less(rest[j - 1], i - 1)) {
      from[k] = --i;
    } else {
      from[k] = n + --j;  // ≥ n: the rest's j-th record
    }
  }
  const size_t first = k;
  tbb::task_group arrays;  // one task per array
  ForEachArray(*this, *this, [&](auto& a, auto&, auto width) {
    arrays.run([&a, &rest, &from, first, n] {
      constexpr size_t stride = decltype(width)::value;
      using Array = std::decay_t<decltype(a)>;
      Array moved(rest.size() * stride);  // the rest's records, sorted, before any is written
      for (size_t r = 0; r < rest.size(); ++r) {
        std::copy_n(a.begin() + size_t(rest[r]) * stride, stride, moved.begin() + r * stride);
      }
      for (size_t p = n; p-- > first;) {
        const size_t f = from[p];
        if (f >= n) {
          std::copy_n(moved.begin() + (f - n) * stride, stride, a.begin() + p * stride);
        } else if (f != p) {
          std::copy_n(a.begin() + f * stride, stride, a.begin() + p * stride);
        }
      }
    });
  });
  arrays.wait();
}

RecordSet MergeRenumbered(const RecordSet& kept, const std::vector<size_t>& rows,
                          const std::vector<int32_t>& renumber, RecordSet added) {
  // Every pass below is parallel: a change keeps most of a project's records, so this is the
  // one step of an ingest whose work is the project's, not the scan's (BM_MergeRenumbered).
  using Key = std::tuple<int32_t, int32_t, int8_t>;
  auto kept_key = [&](size_t i) {  // the key of the i-th kept row, renumbered
    const size_t r = rows[i];
    return Key(renumber[size_t(kept.vossel[r])], kept.scan[r], kept.modality[r]);
  };
  constexpr size_t kGrain = size_t{1} << 15;
  std::atomic<bool> ordered{true};
  tbb::parallel_for(tbb::blocked_range<size_t>(1, std::max<size_t>(rows.size(), 1), kGrain),
                    [&](const tbb::blocked_range<size_t>& r) {
    for (size_t i = r.begin(); i != r.end() && ordered.load(std::memory_order_relaxed); ++i) {
      if (kept_key(i) < kept_key(i - 1)) ordered.store(false, std::memory_order_relaxed);
    }
  });
  if (!ordered) {  // the general path
    RecordSet out = kept.Select(rows, rows.size() + added.size());
    tbb::parallel_for(tbb::blocked_range<size_t>(0, out.size(), kGrain),
                      [&](const tbb::blocked_range<size_t>& r) {
      for (size_t p = r.begin(); p != r.end(); ++p) out.vossel[p] = renumber[size_t(out.vossel[p])];
    });
    out.Append(added);
    out.SortByVossel();
    return out;
  }
  added.SortByVossel();
  const size_t nk = rows.size(), na = added.size(), n = nk + na;
  // place[j]: where added record j goes, after the kept rows of keys up to its own (on equal
  // keys the kept come first) and the j added before it; rising in j.
  std::vector<size_t> place(na);
  tbb::parallel_for(tbb::blocked_range<size_t>(0, na, 1024), [&](const tbb::blocked_range<size_t>& r) {
    for (size_t j = r.begin(); j != r.end(); ++j) {
      const Key a(added.vossel[j], added.scan[j], added.modality[j]);
      size_t lo = 0, hi = nk;
      while (lo < hi) {
        const size_t mid = lo + (hi - lo) / 2;
        if (a < kept_key(mid)) {
          hi = mid;
        } else {
          lo = mid + 1;
        }
      }
      place[j] = lo + j;
    }
  });
  // The merged order as runs: a run of consecutive kept rows that no added record falls
  // between, or of added records placed side by side, each copied by one copy per array (a
  // change keeps whole stretches of a project's records: a record at a time, through a table
  // of where each came from, made the merge four times the memory traffic, BM_MergeRenumbered).
  struct Run {
    size_t src = 0, dst = 0, len = 0;
    bool added = false;
  };
  std::vector<Run> runs;
  auto push = [&runs, kGrain](Run run) {  // long runs in pieces, so that threads share them
    for (; run.len > kGrain; run.src += kGrain, run.dst += kGrain, run.len -= kGrain) {
      runs.push_back({run.src, run.dst, kGrain, run.added});
    }
    runs.push_back(run);
  };
  for (size_t i = 0, j = 0, p = 0; i < nk || j < na;) {
    if (j < na && place[j] == p) {  // added records j.. at places p..
      const size_t j0 = j;
      while (j < na && place[j] == p + (j - j0)) ++j;
      push({j0, p, j - j0, true});
      p += j - j0;
      continue;
    }
    // Kept rows fill the places up to the next added record's (or the end).
    const size_t limit = j < na ? place[j] : n;
    const size_t i0 = i++;
    while (p + (i - i0) < limit && i < nk && rows[i] == rows[i - 1] + 1) ++i;
    push({rows[i0], p, i - i0, false});
    p += i - i0;
  }
  RecordSet out;
  tbb::task_group arrays;  // one task per array, as Select; each copies its runs in parallel
  ForEachArrayOf(
      [&](auto width, auto& dst, const auto& old, const auto& more) {
        arrays.run([&dst, &old, &more, &runs, n] {
          constexpr size_t stride = decltype(width)::value;
          dst.resize(n * stride);
          tbb::parallel_for(tbb::blocked_range<size_t>(0, runs.size(), 16),
                            [&](const tbb::blocked_range<size_t>& r) {
            for (size_t k = r.begin(); k != r.end(); ++k) {
              const Run& run = runs[k];
              const auto* src = run.added ? &more[run.src * stride] : &old[run.src * stride];
              std::copy_n(src, run.len * stride, &dst[run.dst * stride]);
            }
          });
        });
      },
      out, std::as_const(kept), std::as_const(added));
  arrays.wait();
  tbb::parallel_for(tbb::blocked_range<size_t>(0, runs.size(), 16),
                    [&](const tbb::blocked_range<size_t>& r) {
    for (size_t k = r.begin(); k != r.end(); ++k) {  // the kept rows' vossels, renumbered
      const Run& run = runs[k];
      if (run.added) continue;
      int32_t* v = &out.vossel[run.dst];
      for (size_t t = 0; t < run.len; ++t) v[t] = renumber[size_t(v[t])];
    }
  });
  return out;
}

RecordSet RecordSet::Select(const std::vector<size_t>& indices, size_t capacity) const {
  // One task per array: a large set's time goes to the first touch of its new pages (the
  // zeroing resize), which then runs on every thread at once.
  RecordSet out;
  tbb::task_group arrays;
  ForEachArray(out, *this, [&](auto& dst, const auto& src, auto width) {
    arrays.run([&dst, &src, &indices, capacity] {
      constexpr size_t stride = decltype(width)::value;
      dst.reserve(std::max(capacity, indices.size()) * stride);
      dst.resize(indices.size() * stride);
      for (size_t i = 0; i < indices.size(); ++i) {
        std::copy_n(src.begin() + indices[i] * stride, stride, dst.begin() + i * stride);
      }
    });
  });
  arrays.wait();
  return out;
}

}  // namespace vasl::records

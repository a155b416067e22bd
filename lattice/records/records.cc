#include "lattice/records/records.h"

#include <algorithm>
#include <cstdint>
#include <numeric>
#include <tuple>

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

namespace {
// Applies `fn(a.member, b.member, stride)` to every array of two RecordSets, so that the
// operations below list the fields once (pass the same set twice for single-set operations).
template <typename A, typename B, typename Fn>
void ForEachArray(A& a, B& b, Fn&& fn) {
  fn(a.vossel, b.vossel, 1);
  fn(a.scan, b.scan, 1);
  fn(a.modality, b.modality, 1);
  fn(a.value, b.value, kValueChannels);
  fn(a.range_m, b.range_m, 1);
  fn(a.cos_inc, b.cos_inc, 1);
  fn(a.foot_major_m, b.foot_major_m, 1);
  fn(a.foot_minor_m, b.foot_minor_m, 1);
  fn(a.uv_px, b.uv_px, 2);
  fn(a.vis, b.vis, 1);
  fn(a.conf, b.conf, kConfidenceCount);
  fn(a.flags, b.flags, 1);
  fn(a.batch, b.batch, 1);
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
  std::vector<uint32_t> order(n);
  std::iota(order.begin(), order.end(), 0u);
  std::stable_sort(order.begin(), order.end(), [this](uint32_t a, uint32_t b) {
    return std::tie(vossel[a], scan[a], modality[a]) < std::tie(vossel[b], scan[b], modality[b]);
  });
  ForEachArray(*this, *this, [&order, n](auto& a, auto&, int stride) {
    std::decay_t<decltype(a)> out(a.size());
    for (size_t i = 0; i < n; ++i)
      std::copy_n(a.begin() + size_t(order[i]) * stride, stride, out.begin() + i * stride);
    a.swap(out);
  });
}

RecordSet RecordSet::Select(const std::vector<size_t>& indices) const {
  RecordSet out;
  ForEachArray(out, *this, [&indices](auto& dst, const auto& src, int stride) {
    dst.resize(indices.size() * stride);
    for (size_t i = 0; i < indices.size(); ++i) {
      std::copy_n(src.begin() + indices[i] * stride, stride, dst.begin() + i * stride);
    }
  });
  return out;
}

}  // namespace vasl::records

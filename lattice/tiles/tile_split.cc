#include "lattice/tiles/tile_split.h"

#include <numeric>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include "lattice/records/record_grid.h"

namespace vasl::tiles {
namespace {

/// Copies element `from` of every per-vossel geometry array of `src` onto the end of `dst`.
void AppendVossel(const records::VosselGeometry& src, size_t from, records::VosselGeometry& dst) {
  dst.coord.push_back(src.coord[from]);
  if (!src.point_count.empty()) dst.point_count.push_back(src.point_count[from]);
  if (!src.centroid_m.empty()) dst.centroid_m.push_back(src.centroid_m[from]);
  if (!src.normal.empty()) dst.normal.push_back(src.normal[from]);
  if (!src.covariance_m2.empty()) dst.covariance_m2.push_back(src.covariance_m2[from]);
  if (!src.sums.empty()) dst.sums.push_back(src.sums[from]);
  if (!src.frame.empty()) dst.frame.push_back(src.frame[from]);
}

/// Fused values of `vossels` (indices into `fused`'s arrays), in that order.
records::FusedValues GatherFused(const records::FusedValues& fused,
                                 const std::vector<int32_t>& vossels) {
  records::FusedValues out;
  out.profile = fused.profile;
  for (const auto& [modality, fm] : fused.by_modality) {
    records::FusedModality o;
    o.channels = fm.channels;
    o.value.reserve(vossels.size() * fm.channels);
    for (int32_t v : vossels) {
      for (int c = 0; c < fm.channels; ++c) o.value.push_back(fm.value[size_t(v) * fm.channels + c]);
      o.weight.push_back(fm.weight[v]);
      o.uncertainty.push_back(fm.uncertainty[v]);
    }
    out.by_modality.emplace(modality, std::move(o));
  }
  return out;
}

/// Keeps only the channels the tile's records fuse into.
void KeepOwnChannels(const records::RecordSet& recs, records::FusedValues& fused) {
  bool present[records::kModalityCount] = {};
  for (int8_t m : recs.modality) present[int(records::FusedChannelOf(records::Modality(m)))] = true;
  for (auto it = fused.by_modality.begin(); it != fused.by_modality.end();) {
    if (!present[int(it->first)]) it = fused.by_modality.erase(it);
    else ++it;
  }
}

/// Tiles' fused values (each per tile-local vossel, tiles in order, tile t's vossels starting at
/// tile_first[t]) concatenated per channel, then permuted by new_to_old.
records::FusedValues ConcatFused(const std::vector<const records::FusedValues*>& parts,
                                 const std::vector<size_t>& tile_first,
                                 const std::vector<int32_t>& new_to_old) {
  const size_t n = new_to_old.size();
  records::FusedValues concat;
  for (size_t t = 0; t < parts.size(); ++t) {
    if (parts[t] == nullptr) continue;
    if (!parts[t]->profile.empty()) concat.profile = parts[t]->profile;
    for (const auto& [modality, fm] : parts[t]->by_modality) {
      records::FusedModality& o = concat.by_modality[modality];
      o.channels = fm.channels;
      o.value.resize(n * fm.channels, 0.0f);
      o.weight.resize(n, 0.0f);
      o.uncertainty.resize(n, 0.0f);
      for (size_t v = 0; v < tile_first[t + 1] - tile_first[t]; ++v) {
        const size_t g = tile_first[t] + v;
        for (int c = 0; c < fm.channels; ++c) o.value[g * fm.channels + c] = fm.value[v * fm.channels + c];
        o.weight[g] = fm.weight[v];
        o.uncertainty[g] = fm.uncertainty[v];
      }
    }
  }
  return GatherFused(concat, new_to_old);
}

}  // namespace

std::vector<TileKey> TilesOfVossels(const records::VosselGeometry& g, int T) {
  std::vector<TileKey> out(g.size());
  for (size_t v = 0; v < g.size(); ++v) out[v] = TileOf(g.coord[v], T);
  return out;
}

std::map<TileKey, std::vector<int32_t>> VosselsByTile(const records::VosselGeometry& g, int T) {
  std::map<TileKey, std::vector<int32_t>> out;
  for (size_t v = 0; v < g.size(); ++v) out[TileOf(g.coord[v], T)].push_back(int32_t(v));
  return out;
}

TileCutter::TileCutter(const records::VosselGeometry& g, const records::RecordSet& recs,
                       const records::FusedValues& fused, int T,
                       const std::map<std::string, records::FusedValues>* profile_fused)
    : geometry_(g), records_(recs), fused_(fused), profile_fused_(profile_fused),
      by_tile_(VosselsByTile(g, T)), begin_(g.size() + 1, 0) {
  // First record of every vossel (records sorted by vossel).
  for (size_t i = 0; i < recs.size(); ++i) ++begin_[size_t(recs.vossel[i]) + 1];
  for (size_t k = 0; k < g.size(); ++k) begin_[k + 1] += begin_[k];
}

size_t TileCutter::VosselsOf(const TileKey& key) const {
  auto it = by_tile_.find(key);
  return it == by_tile_.end() ? 0 : it->second.size();
}

TileContents TileCutter::Cut(const TileKey& key) const {
  const records::VosselGeometry& g = geometry_;
  TileContents tile;
  tile.key = key;
  tile.geometry.vossel_size_m = g.vossel_size_m;
  tile.fused.profile = fused_.profile;
  auto it = by_tile_.find(tile.key);
  static const std::vector<int32_t> kNone;
  const std::vector<int32_t>& members = it == by_tile_.end() ? kNone : it->second;
  for (int32_t v : members) AppendVossel(g, size_t(v), tile.geometry);
  // Tile-local canonical order; `local[i]` is the new index of members[i].
  const std::vector<int32_t> local = records::CanonicalizeVosselOrder(tile.geometry);
  std::vector<int32_t> by_local(members.size());
  for (size_t i = 0; i < members.size(); ++i) by_local[size_t(local[i])] = members[i];
  std::vector<size_t> picked;
  for (int32_t v : by_local) {
    for (size_t k = begin_[size_t(v)]; k < begin_[size_t(v) + 1]; ++k) picked.push_back(k);
  }
  tile.records = records_.Select(picked);
  // Records were picked in tile-local vossel order, each vossel's in (scan) order.
  size_t at = 0;
  for (size_t l = 0; l < by_local.size(); ++l) {
    const size_t n = begin_[size_t(by_local[l]) + 1] - begin_[size_t(by_local[l])];
    for (size_t k = 0; k < n; ++k) tile.records.vossel[at++] = int32_t(l);
  }
  if (!fused_.by_modality.empty()) tile.fused = GatherFused(fused_, by_local);
  KeepOwnChannels(tile.records, tile.fused);
  if (profile_fused_ != nullptr) {
    for (const auto& [layer, values] : *profile_fused_) {
      records::FusedValues& f = tile.profile_fused[layer];
      f = GatherFused(values, by_local);
      KeepOwnChannels(tile.records, f);
    }
  }
  return tile;
}

std::vector<TileContents> ExtractTiles(
    const records::VosselGeometry& g, const records::RecordSet& recs,
    const records::FusedValues& fused, const std::set<TileKey>& keys, int T,
    const std::map<std::string, records::FusedValues>* profile_fused) {
  const TileCutter cutter(g, recs, fused, T, profile_fused);
  const std::vector<TileKey> ordered(keys.begin(), keys.end());
  std::vector<TileContents> out(ordered.size());
  tbb::parallel_for(tbb::blocked_range<size_t>(0, ordered.size(), 1),
                    [&](const tbb::blocked_range<size_t>& r) {
    for (size_t t = r.begin(); t != r.end(); ++t) out[t] = cutter.Cut(ordered[t]);
  });
  return out;
}

TileAssembler::TileAssembler(double vossel_size_m, size_t vossels, size_t records)
    : vossels_(vossels) {
  out_.geometry.vossel_size_m = vossel_size_m;
  out_.geometry.coord.reserve(vossels);
  out_.records.Reserve(records);
}

void TileAssembler::Add(TileContents&& tile) {
  if (tile_first_.empty()) {  // the arrays the tiles hold, at their final size (no regrowth)
    const records::VosselGeometry& first = tile.geometry;
    records::VosselGeometry& g = out_.geometry;
    if (!first.point_count.empty()) g.point_count.reserve(vossels_);
    if (!first.centroid_m.empty()) g.centroid_m.reserve(vossels_);
    if (!first.normal.empty()) g.normal.reserve(vossels_);
    if (!first.covariance_m2.empty()) g.covariance_m2.reserve(vossels_);
    if (!first.sums.empty()) g.sums.reserve(vossels_);
    if (!first.frame.empty()) g.frame.reserve(vossels_);
  }
  const size_t first_vossel = out_.geometry.size();
  tile_first_.push_back(first_vossel);
  for (size_t v = 0; v < tile.geometry.size(); ++v) AppendVossel(tile.geometry, v, out_.geometry);
  tile.geometry = records::VosselGeometry{};
  for (int32_t& v : tile.records.vossel) v += int32_t(first_vossel);
  out_.records.Append(tile.records);
  tile.records = records::RecordSet{};
  fused_.push_back(std::move(tile.fused));
  profile_fused_.push_back(std::move(tile.profile_fused));
}

Assembled TileAssembler::Finish() {
  std::vector<size_t>& tile_first = tile_first_;
  tile_first.push_back(out_.geometry.size());
  const std::vector<int32_t> old_to_new = records::CanonicalizeVosselOrder(out_.geometry);
  for (int32_t& v : out_.records.vossel) v = old_to_new[size_t(v)];
  out_.records.SortByVossel();
  // Fused values: concatenated per channel, then permuted like the vossels. A profile's layer
  // is assembled when every tile holds it.
  std::vector<int32_t> new_to_old(old_to_new.size());
  for (size_t i = 0; i < old_to_new.size(); ++i) new_to_old[size_t(old_to_new[i])] = int32_t(i);
  const size_t n = fused_.size();
  std::vector<const records::FusedValues*> parts(n);
  for (size_t t = 0; t < n; ++t) parts[t] = &fused_[t];
  out_.fused = ConcatFused(parts, tile_first, new_to_old);
  if (n > 0) {
    for (const auto& [layer, first] : profile_fused_.front()) {
      bool everywhere = true;
      for (size_t t = 0; t < n && everywhere; ++t) {
        auto it = profile_fused_[t].find(layer);
        everywhere = it != profile_fused_[t].end();
        if (everywhere) parts[t] = &it->second;
      }
      if (everywhere) out_.profile_fused[layer] = ConcatFused(parts, tile_first, new_to_old);
    }
  }
  fused_.clear();
  profile_fused_.clear();
  return std::move(out_);
}

Assembled AssembleTiles(std::vector<TileContents>&& tiles, double h) {
  size_t vossels = 0, records = 0;
  for (const TileContents& t : tiles) {
    vossels += t.geometry.size();
    records += t.records.size();
  }
  TileAssembler assembler(h, vossels, records);
  for (TileContents& t : tiles) assembler.Add(std::move(t));
  tiles.clear();
  return assembler.Finish();
}

}  // namespace vasl::tiles

// What a reader holds of a version in memory, and tile groups within a budget (tile_budget.h).
#include "lattice/flows/tile_budget.h"

#include <algorithm>
#include <array>

#include "lattice/records/records.h"

namespace vasl::flows {
namespace {

// One vossel of records::VosselGeometry: coord, point count, centroid, normal, covariance,
// sums and frame.
constexpr int64_t kGeometryBytes =
    int64_t(sizeof(openvdb::Coord) + sizeof(int32_t) + 2 * sizeof(Eigen::Vector3f) +
            sizeof(std::array<float, 6>) + sizeof(records::VosselSums) +
            sizeof(records::VosselFrame));
// Its index grid: a surface fills about an eighth of an 8³ leaf, whose buffer holds all 512
// values (4 bytes each): about 32 bytes a vossel.
constexpr int64_t kIndexGridBytes = 32;
// One fused layer: value, weight and uncertainty of each modality a vossel may hold (RGB,
// LiDAR intensity, IR, radar, derived): at most 5 × (3 + 2) floats, on average far less.
constexpr int64_t kFusedBytes = 40;
// One record of records::RecordSet.
constexpr int64_t kRecordBytes =
    int64_t(3 * sizeof(int32_t) + 2 * sizeof(int8_t) +
            (records::kValueChannels + 5 + 2 + records::kConfidenceCount) * sizeof(float));
// What weighing adds per record (weight, the profile's value) and per vossel (its first record).
constexpr int64_t kWeighingRecordBytes = int64_t((1 + records::kValueChannels) * sizeof(float));
constexpr int64_t kWeighingVosselBytes = int64_t(sizeof(size_t));

}  // namespace

int64_t TileMemoryBytes(const std::map<std::string, store::ManifestEntry>& layers,
                        bool with_records, int fused_layers) {
  int64_t vossels = 0, recs = 0;
  if (auto it = layers.find(store::kLayerGeometry); it != layers.end()) {
    vossels = it->second.vossels;
  }
  if (auto it = layers.find(store::kLayerRecords); it != layers.end()) recs = it->second.records;
  int64_t bytes = vossels * (kGeometryBytes + kIndexGridBytes + fused_layers * kFusedBytes);
  if (with_records) {
    bytes += recs * (kRecordBytes + kWeighingRecordBytes) + vossels * kWeighingVosselBytes;
  }
  return bytes;
}

int64_t VersionMemoryBytes(const store::Manifest& manifest, bool with_records, int fused_layers,
                           const std::set<tiles::TileKey>* among) {
  int64_t bytes = 0;
  for (const auto& [key, layers] : manifest.tiles) {
    if (among == nullptr || among->count(key) != 0) {
      bytes += TileMemoryBytes(layers, with_records, fused_layers);
    }
  }
  return bytes;
}

std::vector<std::set<tiles::TileKey>> TileGroups(const store::Manifest& manifest,
                                                 bool with_records, int fused_layers,
                                                 int64_t budget_bytes,
                                                 const std::set<tiles::TileKey>* among) {
  std::vector<std::set<tiles::TileKey>> groups;
  int64_t held = 0;
  for (const auto& [key, layers] : manifest.tiles) {
    if (among != nullptr && among->count(key) == 0) continue;
    const int64_t bytes = TileMemoryBytes(layers, with_records, fused_layers);
    if (groups.empty() || held + bytes > budget_bytes) {
      groups.emplace_back();
      held = 0;
    }
    groups.back().insert(key);
    held += bytes;
  }
  return groups;
}

std::vector<TileBox> TilesNearestFirst(const store::Manifest& manifest,
                                       const Eigen::Vector3d& eye_m, int tile_vossels,
                                       double vossel_size_m) {
  std::vector<TileBox> out;
  for (const auto& [key, layers] : manifest.tiles) {
    const tiles::Box cells = tiles::BoxOf(key, tile_vossels, vossel_size_m);
    TileBox box;
    box.key = key;
    box.lo_m = cells.min_m;
    box.hi_m = cells.max_m;
    box.near_m = (eye_m.cwiseMax(box.lo_m).cwiseMin(box.hi_m) - eye_m).norm();
    out.push_back(box);
  }
  std::sort(out.begin(), out.end(), [](const TileBox& a, const TileBox& b) {
    return a.near_m != b.near_m ? a.near_m < b.near_m : a.key < b.key;
  });
  return out;
}

std::set<tiles::TileKey> TilesMeeting(const store::Manifest& manifest, const openvdb::Coord& lo,
                                      const openvdb::Coord& hi, int tile_vossels) {
  const tiles::TileKey a = tiles::TileOf(lo, tile_vossels), b = tiles::TileOf(hi, tile_vossels);
  std::set<tiles::TileKey> out;
  for (const auto& [key, layers] : manifest.tiles) {
    if (key.x >= a.x && key.x <= b.x && key.y >= a.y && key.y <= b.y && key.z >= a.z &&
        key.z <= b.z) {
      out.insert(key);
    }
  }
  return out;
}

}  // namespace vasl::flows

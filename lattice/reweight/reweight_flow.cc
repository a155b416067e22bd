#include "lattice/reweight/reweight_flow.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <filesystem>
#include <mutex>
#include <vector>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include "absl/strings/str_cat.h"
#include "lattice/fusion/fuse.h"
#include "lattice/records/record_grid.h"

namespace vasl::reweight {
namespace fs = std::filesystem;

absl::StatusOr<ReweightResult> Reweight(store::ProjectStore& store,
                                        const fusion::WeightingProfile& profile,
                                        const TileProgressFn& progress) {
  const auto t0 = std::chrono::steady_clock::now();
  if (absl::Status s = fusion::ValidateProfile(profile); !s.ok()) return s;
  const int64_t head = store.head_version();
  if (head == 0) {
    return absl::FailedPreconditionError(absl::StrCat(
        "project ", store.name(), " has no version to reweight yet: ingest a scan first"));
  }
  absl::StatusOr<store::Manifest> manifest = store.LoadManifest(head);
  if (!manifest.ok()) return manifest.status();
  ReweightResult out;
  out.layer = store::FusedLayerName(profile.name, profile.version);
  out.profile = profile.name;
  out.revision = profile.version;
  out.tiles = int64_t(manifest->tiles.size());
  for (const auto& [key, layers] : manifest->tiles) {
    auto it = layers.find(store::kLayerRecords);
    if (it != layers.end()) {
      out.records += it->second.records;
      out.vossels += it->second.vossels;
    }
  }
  bool complete = true;
  for (const auto& [key, layers] : manifest->tiles) complete = complete && layers.count(out.layer);
  if (complete) {
    out.version = head;
    out.unchanged = true;
    return out;
  }

  std::vector<std::pair<tiles::TileKey, const std::map<std::string, store::ManifestEntry>*>> todo;
  for (const auto& [key, layers] : manifest->tiles) todo.emplace_back(key, &layers);
  // The tiles with the most records first: a tile's read is one thread's, so a large one
  // started last would keep the others waiting (the commit does not depend on the order).
  auto records_of = [](const std::map<std::string, store::ManifestEntry>& layers) {
    auto it = layers.find(store::kLayerRecords);
    return it == layers.end() ? int64_t{0} : it->second.records;
  };
  std::stable_sort(todo.begin(), todo.end(), [&](const auto& a, const auto& b) {
    return records_of(*a.second) > records_of(*b.second);
  });
  std::vector<std::map<std::string, store::ManifestEntry>> written(todo.size());
  std::vector<absl::Status> status(todo.size());
  store::ObjectStore& objects = store.writable_objects();
  std::atomic<int64_t> done{0};
  std::atomic<bool> stopped{false};
  absl::Status stop;  // the caller's answer that stopped the reweight (under progress_mu)
  std::mutex progress_mu;
  const double h = store.settings().vossel_size_m;
  tbb::parallel_for(tbb::blocked_range<size_t>(0, todo.size(), 1),
                    [&](const tbb::blocked_range<size_t>& r) {
    for (size_t t = r.begin(); t != r.end(); ++t) {
      if (stopped.load(std::memory_order_relaxed)) return;
      const auto& layers = *todo[t].second;
      auto path_of = [&](const char* layer) -> absl::StatusOr<fs::path> {
        auto it = layers.find(layer);
        if (it == layers.end()) {
          return absl::DataLossError(absl::StrCat("version ", head, " tile ",
                                                  tiles::ToString(todo[t].first), " has no ", layer));
        }
        return objects.LocalPath(it->second.object);
      };
      status[t] = [&]() -> absl::Status {
        absl::StatusOr<fs::path> g_path = path_of(store::kLayerGeometry);
        if (!g_path.ok()) return g_path.status();
        absl::StatusOr<fs::path> r_path = path_of(store::kLayerRecords);
        if (!r_path.ok()) return r_path.status();
        absl::StatusOr<records::VosselGeometry> g = records::ReadLattice(*g_path);
        if (!g.ok()) return g.status();
        absl::StatusOr<records::RecordSet> recs = records::ReadRecords(*g, *r_path);
        if (!recs.ok()) return recs.status();
        absl::StatusOr<records::FusedValues> fused = fusion::Fuse(*recs, g->size(), h, profile);
        if (!fused.ok()) return fused.status();
        absl::StatusOr<std::string> bytes = records::EncodeFused(*g, *fused);
        if (!bytes.ok()) return bytes.status();
        absl::StatusOr<store::StoredObject> obj = objects.PutBytes(*bytes);
        if (!obj.ok()) return obj.status();
        written[t][out.layer] = {obj->sha256, int64_t(g->size()), int64_t(recs->size()), obj->bytes};
        return absl::OkStatus();
      }();
      const int64_t n = ++done;
      if (progress) {
        std::lock_guard<std::mutex> lock(progress_mu);
        if (absl::Status s = progress(n, int64_t(todo.size())); !s.ok() && stop.ok()) {
          stop = std::move(s);
          stopped = true;
        }
      }
    }
  });
  if (!stop.ok()) return stop;  // the objects written are garbage for the next collection
  for (const absl::Status& s : status) {
    if (!s.ok()) return s;  // the objects written are garbage for the next collection
  }
  store::CommitPlan plan;
  plan.layers_only = true;
  plan.made_by = absl::StrCat("reweight under profile ", profile.name, " revision ", profile.version);
  for (size_t t = 0; t < todo.size(); ++t) {
    out.bytes_written += written[t][out.layer].bytes;
    plan.put_layers[todo[t].first] = std::move(written[t]);
  }
  absl::StatusOr<int64_t> version = store.Commit(store::Snapshot{}, plan);
  if (!version.ok()) return version.status();
  out.version = *version;
  out.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return out;
}

}  // namespace vasl::reweight

// vasl_bench: the speed figures of the flows users wait for (ingest, reweight, render, record
// IO) on the synthetic room, and the growth of the store over the corridor site, on this
// machine. Run by deploy/bench.sh; speed goals live here, not in timed tests.
// Usage: vasl_bench [--panorama-width W] [--repeat N] [--growth-only] [--tile-vossels T]
//                   [--snapshot-budget-mb M]  (the growth engine's EngineLimits::max_snapshot_bytes)
//                   [--revisit-cache-mb M]    (its and the site's EngineLimits::
//                                              max_revisit_image_bytes)
//                   [--growth-passes N]       (ingests of the corridor timed N times, default 3)
//                   [--site realistic|small [--json PATH]]  (issue "Speed": a site at realistic
//                   size, or small, ingested, fused, reweighted, rebuilt and rendered; alone)
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <map>
#include <string>

#include <malloc.h>
#include <sys/resource.h>
#include <tbb/info.h>

#include "absl/strings/numbers.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_split.h"

#include "lattice/engine.h"
#include "lattice/flows/tile_budget.h"
#include "lattice/fusion/fuse.h"
#include "lattice/records/record_grid.h"
#include "lattice/store/project_store.h"
#include "tests/scenes/corridor_site.h"
#include "tests/scenes/synthetic_scene.h"
#ifdef VASL_HAVE_EMBREE
#include "tests/bench/embree_peer.h"
#endif

namespace {

// Profiles the corridor's (or the --site's) ingests alone, without the scenes' generation
// around them:
//   mkfifo ctl ack; VASL_PERF_CTL=ctl VASL_PERF_ACK=ack \
//     perf record -D -1 --control=fifo:ctl,ack -o ingest.perf vasl_bench --growth-only
// perf starts with its counters off; each ingest turns them on and off again. With
// VASL_PERF_SCANS=2,12 (scan numbers from 1) only those ingests are sampled; with
// VASL_PERF_STEP=reweight the reweight flow's runs are sampled instead of the ingests.
bool PerfReweights() {
  static const char* step = std::getenv("VASL_PERF_STEP");
  return step != nullptr && std::strcmp(step, "reweight") == 0;
}
bool PerfScan(size_t scan_number) {
  if (PerfReweights()) return false;
  static const char* scans = std::getenv("VASL_PERF_SCANS");
  if (scans == nullptr) return true;
  for (absl::string_view n : absl::StrSplit(scans, ',')) {
    size_t k = 0;
    if (absl::SimpleAtoi(n, &k) && k == scan_number) return true;
  }
  return false;
}
void PerfControl(const char* command) {
  static const char* ctl = std::getenv("VASL_PERF_CTL");
  static const char* ack = std::getenv("VASL_PERF_ACK");
  if (ctl == nullptr) return;
  if (FILE* f = std::fopen(ctl, "w")) {
    std::fprintf(f, "%s\n", command);
    std::fclose(f);
  }
  if (ack == nullptr) return;
  if (FILE* f = std::fopen(ack, "r")) {  // perf answers "ack" once the command took effect
    char answer[16];
    (void)std::fgets(answer, sizeof answer, f);
    std::fclose(f);
  }
}

using Clock = std::chrono::steady_clock;
double Since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

int Fail(const absl::Status& s) {
  std::fprintf(stderr, "vasl_bench: %s\n", s.ToString().c_str());
  return 1;
}

/// A memory field of /proc/self/status ("VmHWM:", "VmRSS:"), MB; 0 if unknown.
double StatusMb(const char* field) {
  std::FILE* f = std::fopen("/proc/self/status", "r");
  if (!f) return 0.0;
  char line[256];
  double kb = 0.0;
  const size_t n = std::strlen(field);
  while (std::fgets(line, sizeof(line), f)) {
    if (!std::strncmp(line, field, n)) kb = std::atof(line + n);
  }
  std::fclose(f);
  return kb / 1024.0;
}
/// Peak resident set (VmHWM) of this process since the last ResetPeakRss, MB; 0 if unknown.
double PeakRssMb() { return StatusMb("VmHWM:"); }
/// Resident set (VmRSS) of this process now, MB; 0 if unknown.
double RssMb() { return StatusMb("VmRSS:"); }
/// Resets VmHWM to the current RSS (Linux: "5" to /proc/self/clear_refs).
void ResetPeakRss() {
  if (std::FILE* f = std::fopen("/proc/self/clear_refs", "w")) {
    std::fputs("5", f);
    std::fclose(f);
  }
}

/// CPU seconds (user and system) this process has spent on all its threads.
double CpuSeconds() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return double(u.ru_utime.tv_sec + u.ru_stime.tv_sec) +
         1e-6 * double(u.ru_utime.tv_usec + u.ru_stime.tv_usec);
}

/// Median, least and greatest of `v` (not empty).
struct Spread {
  double median, min, max;
};
Spread SpreadOf(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return {v[v.size() / 2], v.front(), v.back()};
}
std::string Json(const Spread& s) {
  return absl::StrFormat("{\"median\": %.6g, \"min\": %.6g, \"max\": %.6g}", s.median, s.min,
                         s.max);
}

/// Runs of the reweight flow (§7) on a stored project: tile by tile from the record objects on
/// disk, under a new profile revision each time (so that each run fuses and commits).
struct ReweightRuns {
  Spread seconds;
  int64_t records = 0, tiles = 0;
  double peak_mb = 0.0;  ///< peak RSS over the runs
};
absl::StatusOr<ReweightRuns> TimeReweights(vasl::Engine& engine, const std::string& project,
                                           int runs) {
  using namespace vasl;
  fusion::WeightingProfile p;
  p.name = "bench";
  p.alpha = 1.3;
  p.beta = 0.7;
  p.rho = 0.5;
  std::vector<double> seconds;
  ReweightRuns out;
  ResetPeakRss();
  for (int run = 0; run < std::max(1, runs); ++run) {
    p.alpha += 0.1;
    if (auto made = engine.CreateProfile(project, p); !made.ok()) return made.status();
    const auto t0 = Clock::now();
    if (PerfReweights()) PerfControl("enable");
    auto r = engine.Reweight(project, "bench", 0);
    if (PerfReweights()) PerfControl("disable");
    if (!r.ok()) return r.status();
    seconds.push_back(Since(t0));
    out.records = r->records;
    out.tiles = r->tiles;
  }
  out.seconds = SpreadOf(seconds);
  out.peak_mb = PeakRssMb();
  return out;
}

/// Three reweights against the time of a rebuild of the same project.
int ReweightAgainstRebuild(vasl::Engine& engine, const std::string& project, double rebuild_s) {
  absl::StatusOr<ReweightRuns> rw = TimeReweights(engine, project, 3);
  if (!rw.ok()) return Fail(rw.status());
  const Spread& t = rw->seconds;
  std::printf("reweight flow (from disk, %lld tiles): median %.2f s of 3 (%.2f-%.2f), %.1f M "
              "records/s, peak %.0f MB; rebuild / reweight = %.1f\n",
              (long long)rw->tiles, t.median, t.min, t.max, rw->records / t.median / 1e6,
              rw->peak_mb, rebuild_s / t.median);
  return 0;
}

/// Bounded readers (issue "A store that grows"): a 1024×512 render of the stored corridor
/// from its first novel view by a fresh engine that reads the version whole, and by one
/// bounded to an eighth of it (EngineLimits::max_snapshot_bytes): seconds, tile groups, and
/// the memory each added to the process (peak RSS over the RSS before, free heap returned to
/// the system first).
int BoundedRender(const std::filesystem::path& dir, const std::string& project) {
  using namespace vasl;
  auto st = store::ProjectStore::Open(dir / project);
  if (!st.ok()) return Fail(st.status());
  auto manifest = (*st)->LoadManifest((*st)->head_version());
  if (!manifest.ok()) return Fail(manifest.status());
  const int64_t whole = flows::VersionMemoryBytes(*manifest, true, 1);
  const int64_t geometry = flows::VersionMemoryBytes(*manifest, false, 1);
  ::malloc_trim(0);
  const double rss0 = RssMb();
  ResetPeakRss();
  {  // what holding the version whole takes, against the estimate
    auto snap = (*st)->LoadSnapshot((*st)->head_version());
    if (!snap.ok()) return Fail(snap.status());
    ::malloc_trim(0);
    std::printf("bounded render: version estimated at %.1f MB (geometry and fused alone %.1f "
                "MB); loaded whole it holds %.0f MB (%.0f MB at the peak of its load)\n",
                whole / 1e6, geometry / 1e6, RssMb() - rss0, PeakRssMb() - rss0);
  }
  for (const int64_t budget : {whole / 8, int64_t(8) << 30}) {
    EngineLimits limits;
    limits.max_snapshot_bytes = budget;
    auto engine = Engine::Open(dir, limits);
    if (!engine.ok()) return Fail(engine.status());
    RenderRequest req;
    req.pose = scenes::CorridorSite::Default().NovelViews()[0];
    req.width_px = 1024;  // 40 B a pixel: 21 MB an image, so that the version's share shows
    req.height_px = 512;
    ::malloc_trim(0);
    const double before = RssMb();
    ResetPeakRss();
    const auto t0 = Clock::now();
    auto image = (*engine)->Render(project, req);
    if (!image.ok()) return Fail(image.status());
    std::printf("  budget %8.1f MB: %.2f s, %d tile groups reading %lld of %lld tiles, %lld hit "
                "pixels, +%.0f MB RSS\n",
                budget / 1e6, Since(t0), image->tile_groups, (long long)image->tiles_read,
                (long long)image->tiles_total, (long long)image->hit_pixels, PeakRssMb() - before);
  }
  return 0;
}

/// Growth of the store (issue "A store that grows"): every scan of the corridor site ingested
/// one at a time, with its seconds, what it recomputed, its peak RSS and the bytes its commit
/// wrote against the project's total; then a rebuild of the same scans.
int Growth(const std::filesystem::path& dir, int pano_w, int tile_vossels, int64_t budget_mb,
           int64_t revisit_cache_mb, int passes) {
  using namespace vasl;
  EngineLimits limits;
  if (budget_mb > 0) limits.max_snapshot_bytes = budget_mb << 20;
  if (revisit_cache_mb >= 0) limits.max_revisit_image_bytes = revisit_cache_mb << 20;
  auto engine = Engine::Open(dir, limits);
  if (!engine.ok()) return Fail(engine.status());
  store::ProjectSettings settings;
  settings.vossel_size_m = 0.05;
  settings.tile_vossels = tile_vossels;
  if (auto p = (*engine)->CreateProject("growth", settings); !p.ok()) return Fail(p.status());
  const scenes::CorridorSite site = scenes::CorridorSite::Default();
  scenes::LidarSettings lidar;
  lidar.azimuth_steps = 1440;
  lidar.elevation_steps = 720;
  std::printf("\ngrowth: corridor site, %zu stations, h 0.05 m, tiles of %d vossels, engine "
              "budget %lld MB, revisited images kept %lld MB\n",
              site.Stations().size(), settings.tile_vossels,
              (long long)((*engine)->limits().max_snapshot_bytes >> 20),
              (long long)((*engine)->limits().max_revisit_image_bytes >> 20));
  std::printf("%-8s %8s %9s %9s %9s %9s %8s %8s %9s %9s %9s %11s %11s\n", "ingest", "seconds",
              "vossels", "records", "revisited", "refreshed", "pairs", "blocks", "rev_voss%",
              "peak_MB", "added_MB", "written_MB", "total_MB");
  std::vector<double> seconds;
  // Bytes of records objects the commits wrote, and what record segments per batch (README
  // "Storage": an LSM-style layout) would have written of them: the records each change
  // computed (its new sources' and its revisited pairs'), not those carried over unchanged
  // into the tiles it rewrote; measured as the written records bytes in that proportion.
  double records_written_mb = 0.0, segments_mb = 0.0;
  store::Manifest previous;
  for (size_t n = 0; n < site.Stations().size(); ++n) {
    lidar.seed = uint64_t(n + 1);
    auto scan = scenes::MakeScanInput(site, n, lidar, pano_w, 2);
    if (!scan.ok()) return Fail(scan.status());
    // The ingest's own memory: its peak over what the process held before it (the engine's
    // cached HEAD and revisited sources, this scan's input), heap freed earlier returned first.
    ::malloc_trim(0);
    const double rss0 = RssMb();
    ResetPeakRss();
    const double cpu0 = CpuSeconds();
    const bool sampled = PerfScan(n + 1);
    if (sampled) PerfControl("enable");
    auto r = (*engine)->IngestScan("growth", *scan);
    if (sampled) PerfControl("disable");
    if (!r.ok()) return Fail(r.status());
    const double cpu = CpuSeconds() - cpu0;
    const double peak = PeakRssMb();
    auto versions = (*engine)->ListVersions("growth");
    if (!versions.ok()) return Fail(versions.status());
    seconds.push_back(r->seconds);
    // Stage seconds grouped: revisits of older sources, the scan's own sources, the rest.
    double revisit = 0.0, own = 0.0;
    std::string rest, each;  // each: the own sources' seconds, LiDAR first
    for (const auto& [stage, sec] : r->stage_seconds) {
      if (stage.rfind("revisit", 0) == 0) {
        revisit += sec;
      } else if (stage.rfind("records of", 0) == 0) {
        own += sec;
        each += absl::StrFormat("%s%.2f", each.empty() ? "" : " + ", sec);
      } else {
        rest += absl::StrFormat(" %s %.2f;", stage, sec);
      }
    }
    std::printf("%-8s %8.2f %9lld %9lld %9lld %9lld %8lld %8lld %9.1f %9.0f %9.0f %11.1f %11.1f   "
                "cpu %.2f s (%.2f cores); revisits %.2f; own sources %.2f (%s);%s\n",
                scan->scan_name.c_str(), r->seconds, (long long)r->vossel_count,
                (long long)r->record_count, (long long)r->sources_revisited,
                (long long)r->sources_refreshed, (long long)r->pairs_revisited,
                (long long)r->blocks_revisited,
                100.0 * double(r->vossels_revisited) /
                    double(std::max<int64_t>(1, r->vossels_in_blocks)),
                peak, peak - rss0,
                r->bytes_written / 1e6,
                versions->back().bytes_total / 1e6, cpu, cpu / std::max(1e-9, r->seconds), revisit, own, each.c_str(),
                rest.c_str());
    auto st = store::ProjectStore::Open(dir / "growth");
    if (!st.ok()) return Fail(st.status());
    auto manifest = (*st)->LoadManifest(r->version);
    if (!manifest.ok()) return Fail(manifest.status());
    double records_mb = 0.0;
    std::map<std::string, double> layer_mb;  // every layer's objects this commit wrote
    for (const auto& [key, layers] : manifest->tiles) {
      auto was = previous.tiles.find(key);
      for (const auto& [layer, entry] : layers) {
        auto before = was == previous.tiles.end() ? nullptr : &was->second;
        if (before == nullptr || !before->count(layer) ||
            before->at(layer).object != entry.object) {
          layer_mb[layer] += entry.bytes / 1e6;
        }
      }
    }
    records_mb = layer_mb[store::kLayerRecords];
    std::string layers_written;
    for (const auto& [layer, mb] : layer_mb) {
      layers_written += absl::StrFormat(" %s %.1f;", layer, mb);
    }
    const double share =
        r->records_rewritten > 0 ? double(r->records_computed) / double(r->records_rewritten)
                                 : 1.0;
    std::printf("         records: %lld computed of %lld in the rewritten tiles; %.1f MB of "
                "records objects written, %.1f MB as segments per batch; tile objects written "
                "(MB):%s\n",
                (long long)r->records_computed, (long long)r->records_rewritten, records_mb,
                records_mb * share, layers_written.c_str());
    const store::CommitTimes& ct = r->commit_times;
    std::printf("         commit: thread s cut %.3f, encode geometry %.3f records %.3f fused "
                "%.3f, put %.3f; wall s tiles %.3f, reach %.3f, sync %.3f, catalog %.3f, HEAD "
                "%.3f, collect %.3f\n",
                ct.cut_s, ct.geometry_s, ct.records_s, ct.fused_s, ct.put_s, ct.tiles_wall_s,
                ct.reach_wall_s, ct.sync_wall_s, ct.catalog_wall_s, ct.head_wall_s,
                ct.collect_wall_s);
    records_written_mb += records_mb;
    segments_mb += records_mb * share;
    previous = std::move(*manifest);
  }
  std::printf("records objects written by all commits %.1f MB; as segments per batch %.1f MB\n",
              records_written_mb, segments_mb);
  if (seconds.size() >= 2) {
    double total = 0.0;
    for (double s : seconds) total += s;
    std::printf("last scan / second scan: %.2f (target <= 1.3); all %zu ingests %.1f s\n",
                seconds.back() / seconds[1], seconds.size(), total);
  }
  // One pass's ratio moves by a fifth between runs on a shared machine: the same ingests,
  // each pass into a fresh engine (its caches empty), give per-scan medians.
  std::vector<std::vector<double>> by_pass{seconds};
  for (int pass = 1; pass < passes; ++pass) {
    const std::filesystem::path pass_dir =
        dir.parent_path() / ("growth-pass-" + std::to_string(pass));
    auto timed = Engine::Open(pass_dir, limits);
    if (!timed.ok()) return Fail(timed.status());
    if (auto p = (*timed)->CreateProject("growth", settings); !p.ok()) return Fail(p.status());
    std::vector<double> pass_seconds;
    for (size_t n = 0; n < site.Stations().size(); ++n) {
      lidar.seed = uint64_t(n + 1);
      auto scan = scenes::MakeScanInput(site, n, lidar, pano_w, 2);
      if (!scan.ok()) return Fail(scan.status());
      auto r = (*timed)->IngestScan("growth", *scan);
      if (!r.ok()) return Fail(r.status());
      pass_seconds.push_back(r->seconds);
    }
    by_pass.push_back(std::move(pass_seconds));
    timed->reset();
    std::filesystem::remove_all(pass_dir);
  }
  if (by_pass.size() > 1 && seconds.size() >= 2) {
    std::printf("per-scan seconds over %zu passes, median (min-max):", by_pass.size());
    std::vector<double> median(seconds.size());
    for (size_t n = 0; n < seconds.size(); ++n) {
      std::vector<double> v;
      for (const auto& pass : by_pass) v.push_back(pass[n]);
      std::sort(v.begin(), v.end());
      median[n] = v[v.size() / 2];
      std::printf(" %.2f (%.2f-%.2f)", median[n], v.front(), v.back());
    }
    std::printf("\nlast scan / second scan, of the medians: %.2f (target <= 1.3); by pass:",
                median.back() / median[1]);
    for (const auto& pass : by_pass) std::printf(" %.2f", pass.back() / pass[1]);
    std::printf("\n");
  }
  auto versions = (*engine)->ListVersions("growth");
  if (versions.ok() && !versions->empty()) {
    int64_t written = 0;
    for (const store::VersionInfo& v : *versions) written += v.bytes_written;
    size_t objects = 0;
    for (const auto& e : std::filesystem::directory_iterator(dir / "growth" / "objects")) {
      objects += e.is_regular_file() ? 1 : 0;
    }
    std::printf("tiles %lld, objects on disk %zu, bytes written by all commits %.1f MB, "
                "project %.1f MB\n",
                (long long)versions->back().tile_count, objects, written / 1e6,
                versions->back().bytes_total / 1e6);
  }
  ResetPeakRss();
  auto rebuilt = (*engine)->Rebuild("growth");
  if (!rebuilt.ok()) return Fail(rebuilt.status());
  std::printf("rebuild of %zu scans: %.2f s, peak %.0f MB\n", site.Stations().size(),
              rebuilt->seconds, PeakRssMb());
  if (int rc = ReweightAgainstRebuild(**engine, "growth", rebuilt->seconds); rc != 0) return rc;
  return BoundedRender(dir, "growth");
}

/// Issue "Speed": the render's peer. Embree traces the same site as triangles with the same
/// equirect rays on the same TBB threads (tests/bench/embree_peer.h): the analytic scene's boxes
/// and the stored lattice's surfels (the data vasl marches), each with rtcIntersect1 per ray and
/// rtcIntersect8 per packet, `repeat` runs. Prints rays/s beside vasl's, and how far vasl's
/// depth lies from Embree's on the analytic boxes; returns the figures as a JSON object
/// ("null" where libembree-dev is not installed).
absl::StatusOr<std::string> EmbreePeers(const vasl::scenes::CorridorSite& site,
                                        vasl::store::ProjectStore& st,
                                        const vasl::RenderRequest& req, int repeat,
                                        const std::vector<float>& vasl_depth_m, double h) {
#ifdef VASL_HAVE_EMBREE
  using namespace vasl;
  std::vector<scenes::Aabb> boxes{site.Bounds()};
  for (const scenes::CorridorSolid& solid : site.Solids()) boxes.push_back(solid.box);
  auto snap = st.LoadSnapshot(st.head_version());
  if (!snap.ok()) return snap.status();
  const double surfel_scale = 1.5;  // overlapping squares: no gaps between neighbours
  std::string json = "{";
  for (const auto& [name, mesh] :
       {std::pair<std::string, bench::TriangleMesh>{"boxes", bench::BoxesAsTriangles(boxes)},
        {"surfels", bench::SurfelsAsTriangles((*snap)->geometry, surfel_scale)}}) {
    const bench::EmbreeScene scene(mesh);
    json += absl::StrFormat("%s\"%s\": {\"triangles\": %zu, \"build_s\": %.4f", 
                            json.size() > 1 ? ", " : "", name, mesh.TriangleCount(),
                            scene.build_seconds());
    for (const int packet : {1, 8}) {
      std::vector<double> rate;
      bench::PeerTrace trace;
      for (int i = 0; i < std::max(1, repeat); ++i) {
        trace = scene.TraceEquirect(req.pose, req.width_px, req.height_px, packet,
                                    req.max_range_m);
        rate.push_back(double(req.width_px) * req.height_px / trace.seconds);
      }
      const Spread r = SpreadOf(rate);
      std::printf("embree %-7s (%zu triangles, BVH %.2f s), rtcIntersect%d: %.2f M rays/s "
                  "(%.2f-%.2f), %.1f%% of pixels hit\n",
                  name.c_str(), mesh.TriangleCount(), scene.build_seconds(), packet,
                  r.median / 1e6, r.min / 1e6, r.max / 1e6,
                  100.0 * trace.hit_pixels / trace.depth_m.size());
      json += absl::StrFormat(", \"intersect%d_rays_per_s\": %s", packet, Json(r));
      if (name != "boxes" || packet != 1) continue;
      // vasl's depth against the analytic scene's: where both hit, and where one alone does.
      std::vector<double> diff;
      int64_t only_vasl = 0, only_embree = 0;
      for (size_t p = 0; p < trace.depth_m.size(); ++p) {
        const bool a = std::isfinite(vasl_depth_m[p]), b = std::isfinite(trace.depth_m[p]);
        if (a && b) diff.push_back(std::abs(double(vasl_depth_m[p]) - trace.depth_m[p]));
        only_vasl += a && !b;
        only_embree += b && !a;
      }
      std::sort(diff.begin(), diff.end());
      const auto within = [&](double tol) {
        return double(std::upper_bound(diff.begin(), diff.end(), tol) - diff.begin()) /
               std::max<size_t>(1, diff.size());
      };
      const double median = diff.empty() ? 0.0 : diff[diff.size() / 2];
      std::printf("  vasl's depth vs the boxes': median |dz| %.4f m, %.2f%% within h, %.2f%% "
                  "within 2h; pixels hit by vasl alone %lld, by Embree alone %lld\n",
                  median, 100.0 * within(h), 100.0 * within(2 * h), (long long)only_vasl,
                  (long long)only_embree);
      json += absl::StrFormat(
          ", \"vasl_depth_median_abs_diff_m\": %.5f, \"vasl_depth_within_h\": %.5f, "
          "\"vasl_depth_within_2h\": %.5f",
          median, within(h), within(2 * h));
    }
    json += "}";
  }
  return json + "}";
#else
  (void)site, (void)st, (void)req, (void)repeat, (void)vasl_depth_m, (void)h;
  std::printf("embree: not installed (deploy/bench.sh installs libembree-dev): no render peer\n");
  return std::string("null");
#endif
}

/// Issue "Speed": a site ingested through the library at realistic size (`realistic`: the
/// corridor's first 6 stations, each a LiDAR grid of 2048×1024 returns and a 4096×2048 RGB
/// panorama, h = 2 cm) or small (LiDAR 512×256, RGB 1024×512, h = 5 cm: under a minute).
/// Prints and writes to `json_path`: per scan points/s and seconds per stage; fusion over the
/// version's records in memory (multiply-only and general exponents with proximity); the
/// reweight flow from disk against a rebuild; an equirect render; bytes per record on disk;
/// peak RSS of each step. Medians and spread over `repeat` runs where a step repeats.
int Site(const std::filesystem::path& dir, bool realistic, int repeat,
         const std::string& json_path, int64_t revisit_cache_mb) {
  using namespace vasl;
  const int lidar_w = realistic ? 2048 : 512, pano_w = realistic ? 4096 : 1024;
  const double h = realistic ? 0.02 : 0.05;
  const size_t stations = 6;
  const int cores = tbb::info::default_concurrency();
  EngineLimits limits;
  if (revisit_cache_mb >= 0) limits.max_revisit_image_bytes = revisit_cache_mb << 20;
  auto engine = Engine::Open(dir, limits);
  if (!engine.ok()) return Fail(engine.status());
  store::ProjectSettings settings;
  settings.vossel_size_m = h;
  if (auto p = (*engine)->CreateProject("site", settings); !p.ok()) return Fail(p.status());
  const scenes::CorridorSite site = scenes::CorridorSite::Default();
  scenes::LidarSettings lidar;
  lidar.azimuth_steps = lidar_w;
  lidar.elevation_steps = lidar_w / 2;
  std::printf("\nsite (%s): corridor stations 1-%zu, LiDAR %dx%d, RGB %dx%d, h %.2f m, %d cores, "
              "revisited images kept %lld MB\n",
              realistic ? "realistic" : "small", stations, lidar_w, lidar_w / 2, pano_w,
              pano_w / 2, h, cores,
              (long long)((*engine)->limits().max_revisit_image_bytes >> 20));
  std::string json = absl::StrFormat(
      "{\n  \"site\": \"%s\", \"cores\": %d, \"vossel_m\": %.3f, \"lidar\": [%d, %d], "
      "\"rgb\": [%d, %d],\n  \"ingest\": [",
      realistic ? "realistic" : "small", cores, h, lidar_w, lidar_w / 2, pano_w, pano_w / 2);
  int64_t records = 0;
  double ingest_peak = 0.0;
  for (size_t n = 0; n < stations; ++n) {
    lidar.seed = uint64_t(n + 1);
    auto scan = scenes::MakeScanInput(site, n, lidar, pano_w, 2);
    if (!scan.ok()) return Fail(scan.status());
    const size_t points = scan->lidar.xyz_sensor_m.size() / 3;
    ResetPeakRss();
    const bool sampled = PerfScan(n + 1);
    if (sampled) PerfControl("enable");
    auto r = (*engine)->IngestScan("site", *scan);
    if (sampled) PerfControl("disable");
    if (!r.ok()) return Fail(r.status());
    ingest_peak = std::max(ingest_peak, PeakRssMb());
    records = r->record_count;
    std::printf("%-8s %7.2f s %9zu points %6.2f M points/s (%.2f per core) %9lld records  ",
                scan->scan_name.c_str(), r->seconds, points, points / r->seconds / 1e6,
                points / r->seconds / 1e6 / cores, (long long)r->record_count);
    std::string stages;
    for (const auto& [stage, sec] : r->stage_seconds) {
      std::printf(" %s %.2f;", stage.c_str(), sec);
      stages += absl::StrFormat("%s\"%s\": %.4f", stages.empty() ? "" : ", ", stage, sec);
    }
    std::printf("\n");
    json += absl::StrFormat(
        "%s\n    {\"scan\": \"%s\", \"seconds\": %.4f, \"points\": %zu, \"points_per_s\": %.6g, "
        "\"records\": %lld, \"peak_rss_mb\": %.0f, \"stages_s\": {%s}}",
        n == 0 ? "" : ",", scan->scan_name, r->seconds, points, points / r->seconds,
        (long long)r->record_count, PeakRssMb(), stages);
  }
  json += "\n  ],\n";

  // Fusion over the version's records in memory: a reweight's computation (§7).
  auto st = store::ProjectStore::Open(dir / "site");
  if (!st.ok()) return Fail(st.status());
  auto manifest = (*st)->LoadManifest((*st)->head_version());
  if (!manifest.ok()) return Fail(manifest.status());
  int64_t record_bytes = 0;
  for (const auto& [key, layers] : manifest->tiles) {
    if (auto it = layers.find(store::kLayerRecords); it != layers.end()) {
      record_bytes += it->second.bytes;
    }
  }
  {
    auto snap = (*st)->LoadSnapshot((*st)->head_version());
    if (!snap.ok()) return Fail(snap.status());
    fusion::WeightingProfile general;
    general.alpha = 1.3;
    general.beta = 0.7;
    general.rho = 0.5;
    general.kappa = {2.5, 1.5, 0.5, 1.2, 0.8, 1.7};
    general.proximity_m = 2.0;
    json += "  \"fusion_in_memory_records_per_s\": {";
    for (const auto& [name, profile] :
         {std::pair<const char*, fusion::WeightingProfile>{"multiply_only", {}},
          {"general", general}}) {
      std::vector<double> rate;
      for (int i = 0; i < repeat; ++i) {
        const auto t0 = Clock::now();
        auto fused = fusion::Fuse((*snap)->records, (*snap)->geometry.size(), h, profile);
        if (!fused.ok()) return Fail(fused.status());
        rate.push_back(double((*snap)->records.size()) / Since(t0));
      }
      const Spread r = SpreadOf(rate);
      std::printf("fusion in memory, %s: %.1f M records/s (%.1f-%.1f)\n", name, r.median / 1e6,
                  r.min / 1e6, r.max / 1e6);
      json += absl::StrFormat("%s\"%s\": %s", *name == 'm' ? "" : ", ", name, Json(r));
    }
    json += "},\n";
  }

  // The reweight flow from disk against one rebuild.
  absl::StatusOr<ReweightRuns> reweights = TimeReweights(**engine, "site", repeat);
  if (!reweights.ok()) return Fail(reweights.status());
  const double reweight_peak = reweights->peak_mb;
  ResetPeakRss();
  auto rebuilt = (*engine)->Rebuild("site");
  if (!rebuilt.ok()) return Fail(rebuilt.status());
  const double rebuild_peak = PeakRssMb();
  const Spread& rw = reweights->seconds;
  std::printf("reweight from disk: %.2f s (%.2f-%.2f), %.1f M records/s, peak %.0f MB; rebuild "
              "%.1f s (peak %.0f MB) = %.0fx the reweight\n",
              rw.median, rw.min, rw.max, records / rw.median / 1e6, reweight_peak,
              rebuilt->seconds, rebuild_peak, rebuilt->seconds / rw.median);
  json += absl::StrFormat(
      "  \"reweight_from_disk_s\": %s, \"reweight_records_per_s\": %.6g, "
      "\"reweight_peak_rss_mb\": %.0f,\n  \"rebuild_s\": %.4f, \"rebuild_peak_rss_mb\": %.0f, "
      "\"rebuild_over_reweight\": %.4g,\n",
      Json(rw), records / rw.median, reweight_peak, rebuilt->seconds, rebuild_peak,
      rebuilt->seconds / rw.median);

  // An equirect render from the first novel view, and the record store's size on disk.
  RenderRequest req;
  req.pose = site.NovelViews()[0];
  req.width_px = pano_w;
  req.height_px = pano_w / 2;
  std::vector<double> rays;
  std::vector<float> depth_m;  // the last render's, for the peer's agreement
  ResetPeakRss();
  for (int i = 0; i < std::max(1, repeat); ++i) {
    const auto t0 = Clock::now();
    auto image = (*engine)->Render("site", req);
    if (!image.ok()) return Fail(image.status());
    rays.push_back(double(req.width_px) * req.height_px / Since(t0));
    depth_m = std::move(image->depth_m);
  }
  const Spread ry = SpreadOf(rays);
  const double render_peak = PeakRssMb();
  std::printf("render %dx%d: %.2f M rays/s (%.2f-%.2f) on %d threads, peak %.0f MB\n",
              req.width_px, req.height_px, ry.median / 1e6, ry.min / 1e6, ry.max / 1e6, cores,
              render_peak);
  absl::StatusOr<std::string> peers = EmbreePeers(site, **st, req, repeat, depth_m, h);
  if (!peers.ok()) return Fail(peers.status());
  std::printf("records on disk: %lld records, %.1f bytes/record; peak RSS of an ingest %.0f MB\n",
              (long long)records, double(record_bytes) / records, ingest_peak);
  json += absl::StrFormat(
      "  \"render\": {\"width\": %d, \"height\": %d, \"threads\": %d, \"rays_per_s\": %s, "
      "\"peak_rss_mb\": %.0f},\n  \"render_peers\": %s,\n"
      "  \"records\": %lld, \"record_bytes_on_disk\": %lld, \"bytes_per_record\": %.3f,\n"
      "  \"ingest_peak_rss_mb\": %.0f\n}\n",
      req.width_px, req.height_px, cores, Json(ry), render_peak, *peers, (long long)records,
      (long long)record_bytes, double(record_bytes) / records, ingest_peak);
  if (!json_path.empty()) {
    std::FILE* f = std::fopen(json_path.c_str(), "w");
    if (!f) return Fail(absl::InternalError("cannot write " + json_path));
    std::fputs(json.c_str(), f);
    std::fclose(f);
    std::printf("figures written to %s\n", json_path.c_str());
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  using namespace vasl;
  int pano_w = 2048, repeat = 5;
  bool growth_only = false;
  int tile_vossels = 64;
  int64_t budget_mb = 0, revisit_cache_mb = -1;
  int growth_passes = 3;
  std::string site, json_path;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--growth-only")) growth_only = true;
    else if (i + 1 < argc && !std::strcmp(argv[i], "--panorama-width")) pano_w = std::atoi(argv[++i]);
    else if (i + 1 < argc && !std::strcmp(argv[i], "--repeat")) repeat = std::atoi(argv[++i]);
    else if (i + 1 < argc && !std::strcmp(argv[i], "--tile-vossels")) tile_vossels = std::atoi(argv[++i]);
    else if (i + 1 < argc && !std::strcmp(argv[i], "--snapshot-budget-mb")) budget_mb = std::atoll(argv[++i]);
    else if (i + 1 < argc && !std::strcmp(argv[i], "--revisit-cache-mb"))
      revisit_cache_mb = std::atoll(argv[++i]);
    else if (i + 1 < argc && !std::strcmp(argv[i], "--growth-passes"))
      growth_passes = std::max(1, std::atoi(argv[++i]));
    else if (i + 1 < argc && !std::strcmp(argv[i], "--site")) site = argv[++i];
    else if (i + 1 < argc && !std::strcmp(argv[i], "--json")) json_path = argv[++i];
    else {
      // An unknown flag, or one without its value, is an error: silently running the whole
      // benchmark (minutes) on a mistyped flag is what a user least expects.
      const bool help = !std::strcmp(argv[i], "--help") || !std::strcmp(argv[i], "-h");
      std::fprintf(help ? stdout : stderr,
                   "%s%s"
                   "usage: vasl_bench [--panorama-width W] [--repeat N] [--growth-only]\n"
                   "                  [--tile-vossels T] [--snapshot-budget-mb M]\n"
                   "                  [--revisit-cache-mb M] [--growth-passes N]\n"
                   "                  [--site realistic|small [--json PATH]]\n",
                   help ? "" : "vasl_bench: unknown flag or missing value: ",
                   help ? "" : (std::string(argv[i]) + "\n").c_str());
      return help ? 0 : 2;
    }
  }
  const double h = 0.05;
  const std::filesystem::path dir = std::filesystem::temp_directory_path() / ("vasl-bench-" + std::to_string(::getpid()));
  std::filesystem::remove_all(dir);
  if (!site.empty()) {
    if (site != "realistic" && site != "small") {
      std::fprintf(stderr, "vasl_bench: --site takes realistic or small, not %s\n", site.c_str());
      return 2;
    }
    const int rc = Site(dir / "site-engine", site == "realistic", std::max(1, repeat), json_path,
                         revisit_cache_mb);
    std::filesystem::remove_all(dir);
    return rc;
  }
  std::printf("vasl_bench: %d threads, vossel %.2f m, panoramas %dx%d, LiDAR 1440x720 per scan\n",
              tbb::info::default_concurrency(), h, pano_w, pano_w / 2);
  if (growth_only) {
    const int rc = Growth(dir / "growth-engine", pano_w, tile_vossels, budget_mb, revisit_cache_mb,
                          growth_passes);
    std::filesystem::remove_all(dir);
    return rc;
  }

  auto engine = Engine::Open(dir);
  if (!engine.ok()) return Fail(engine.status());
  store::ProjectSettings settings;
  settings.vossel_size_m = h;
  if (auto p = (*engine)->CreateProject("bench", settings); !p.ok()) return Fail(p.status());
  const scenes::SyntheticRoom room = scenes::SyntheticRoom::Default();
  scenes::LidarSettings lidar;
  lidar.azimuth_steps = 1440;
  lidar.elevation_steps = 720;
  std::printf("\n%-8s %8s %9s %8s   stages (s)\n", "ingest", "seconds", "vossels", "records");
  for (size_t n = 0; n < room.Stations().size(); ++n) {
    lidar.seed = uint64_t(n + 1);
    auto scan = scenes::MakeScanInput(room, n, lidar, pano_w, 2);
    if (!scan.ok()) return Fail(scan.status());
    auto r = (*engine)->IngestScan("bench", *scan);
    if (!r.ok()) return Fail(r.status());
    std::printf("%-8s %8.2f %9lld %8lld  ", scan->scan_name.c_str(), r->seconds, (long long)r->vossel_count,
                (long long)r->record_count);
    for (const auto& [stage, s] : r->stage_seconds) std::printf(" %s %.2f;", stage.c_str(), s);
    std::printf("\n");
  }

  // Reweight = fuse the stored records under another profile (§7): one pass over the records.
  auto st = store::ProjectStore::Open(dir / "bench");
  if (!st.ok()) return Fail(st.status());
  auto snap = (*st)->LoadSnapshot((*st)->head_version());
  if (!snap.ok()) return Fail(snap.status());
  const records::RecordSet& recs = (*snap)->records;
  std::printf("\n%-34s %10s %14s\n", "reweight (fusion over records)", "ms", "M records/s");
  fusion::WeightingProfile unit;
  unit.beta = 1.0;
  unit.alpha = 1.0;
  fusion::WeightingProfile general;
  general.alpha = 1.3;
  general.beta = 0.7;
  general.rho = 0.5;
  general.kappa = {2.5, 1.5, 0.5, 1.2};
  general.proximity_m = 2.0;
  for (const auto& [name, profile] : {std::pair<const char*, fusion::WeightingProfile>{"multiply-only (exponents 0/1/2)", unit},
                                      {"general exponents + proximity", general}}) {
    double best = 1e30;
    for (int i = 0; i < repeat; ++i) {
      const auto t0 = Clock::now();
      auto fused = fusion::Fuse(recs, (*snap)->geometry.size(), h, profile);
      if (!fused.ok()) return Fail(fused.status());
      best = std::min(best, Since(t0));
    }
    std::printf("%-34s %10.1f %14.1f\n", name, best * 1e3, recs.size() / best / 1e6);
  }

  // Render (§8).
  std::printf("\n%-20s %10s %12s\n", "render", "ms", "M rays/s");
  for (int w : {1024, 2048, 4096}) {
    RenderRequest req;
    req.pose = room.NovelViews()[0];
    req.width_px = w;
    req.height_px = w / 2;
    double best = 1e30;
    for (int i = 0; i < std::max(1, repeat / 2); ++i) {
      const auto t0 = Clock::now();
      auto image = (*engine)->Render("bench", req);
      if (!image.ok()) return Fail(image.status());
      best = std::min(best, Since(t0));
    }
    std::printf("%4dx%-15d %10.1f %12.2f\n", w, w / 2, best * 1e3, double(w) * (w / 2) / best / 1e6);
  }

  // Record file IO (records.vdb).
  const std::filesystem::path file = dir / "records-bench.vdb";
  auto t0 = Clock::now();
  if (auto s = records::WriteRecords((*snap)->geometry, recs, file); !s.ok()) return Fail(s);
  const double write_s = Since(t0);
  t0 = Clock::now();
  auto back = records::ReadRecords((*snap)->geometry, file);
  if (!back.ok()) return Fail(back.status());
  const double read_s = Since(t0);
  const double bytes = double(std::filesystem::file_size(file));
  std::printf("\nrecords.vdb: %zu records, %.1f bytes/record on disk, write %.0f ms (%.1f M rec/s), "
              "read %.0f ms (%.1f M rec/s)\n", recs.size(), bytes / recs.size(), write_s * 1e3,
              recs.size() / write_s / 1e6, read_s * 1e3, recs.size() / read_s / 1e6);
  if (int rc = Growth(dir / "growth-engine", pano_w, tile_vossels, budget_mb, revisit_cache_mb,
                      growth_passes);
      rc != 0) {
    return rc;
  }
  std::filesystem::remove_all(dir);
  return 0;
}

#include "lattice/flows/change.h"

#include <algorithm>
#include <cmath>
#include <initializer_list>
#include <limits>
#include <map>
#include <memory>
#include <optional>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_pipeline.h>
#include <tbb/parallel_reduce.h>
#include <tbb/task_arena.h>

#include "absl/strings/str_cat.h"
#include "lattice/fusion/fuse.h"
#include "lattice/geometry/footprint.h"
#include "lattice/ingest/backproject.h"
#include "lattice/ingest/sample.h"
#include "lattice/ingest/visibility.h"
#include "lattice/records/record_grid.h"
#include "lattice/reweight/profiles.h"
#include "lattice/tiles/tile_split.h"

namespace vasl::flows::internal {
namespace {

/// How a stored source's visibility tests read its depth panorama (as its records did).
ingest::DepthView ViewOf(const SourceRef& s) {
  return s.returns()
             ? ingest::LidarDepthView(size_t(std::max<int64_t>(0, s.info.point_count)),
                                      s.info.divergence_rad)
             : ingest::CameraDepthView(CameraOf(s.info, 0), s.info.width_px, s.info.height_px);
}

/// Angular pitch (radians, the larger axis) of a source's depth panorama: the Δ of its
/// visibility tolerance.
double DepthPixelRad(const SourceRef& s) {
  const geometry::EquirectSize size = ViewOf(s).size;
  return std::max(geometry::AzimuthPitchRad(size), geometry::ElevationPitchRad(size));
}

/// The pixel span of a source's slope-scaled tolerance (ComputeVisibility's `slope_pixels`
/// times its pitch): a camera's tests read its dilated panorama.
double TolerancePixelRad(const SourceRef& s) {
  return (s.returns() ? 1.0 : 1.0 + ingest::CameraSampleRadiusPx()) * DepthPixelRad(s);
}

/// Directions to widen a source's caps by: pixel rounding of the splats and of the visibility
/// test (2 pixels), a camera's dilation, and the splat's own angular growth (the beam
/// divergence for a LiDAR, one pixel for a camera).
double AngularMarginRad(const SourceRef& s) {
  const double pixel = DepthPixelRad(s);
  if (s.returns()) return 2.0 * pixel + s.info.divergence_rad;
  return (2.0 + ingest::CameraSampleRadiusPx() + 1.0) * pixel + s.info.divergence_rad;
}

/// True when some pixel of `depth` that a direction within `radius_rad` of `d_sensor` (unit,
/// sensor frame) falls in holds a depth below `threshold_m`.
bool NearerInCap(const ingest::DepthPanorama& depth, const Eigen::Vector3d& d_sensor,
                 double radius_rad, double threshold_m) {
  const int W = depth.size.width_px;
  const tiles::PixelSpan span = tiles::CapPixelSpan(d_sensor, radius_rad, depth.size);
  for (int j = span.row_first; j <= span.row_last; ++j) {
    const float* row = &depth.depth_m[size_t(j) * size_t(W)];
    for (int n = 0, i = span.col_first; n < span.col_count; ++n, i = i + 1 == W ? 0 : i + 1) {
      if (double(row[i]) < threshold_m) return true;
    }
  }
  return false;
}

}  // namespace

absl::Status StageClock::Start(const std::string& name, double fraction) {
  Finish();
  running_ = name;
  t0_ = Clock::now();
  return stage_ ? stage_(name, fraction) : absl::OkStatus();
}

void StageClock::Finish() {
  if (running_.empty()) return;
  result_.stage_seconds.emplace_back(running_,
                                     std::chrono::duration<double>(Clock::now() - t0_).count());
  running_.clear();
}

std::vector<SourceRef> SourcesOf(const std::vector<store::ScanInfo>& scans) {
  std::vector<SourceRef> out;
  for (const store::ScanInfo& scan : scans) {
    for (const store::SourceInfo& src : scan.sources) out.push_back({src, scan.batch});
  }
  std::sort(out.begin(), out.end(),
            [](const SourceRef& a, const SourceRef& b) { return a.info.id < b.info.id; });
  return out;
}

std::vector<ChangedBlock> ChangedBlocks(const records::VosselGeometry& old,
                                        const records::VosselGeometry& now,
                                        const std::vector<int32_t>& old_to_new, int T,
                                        std::set<tiles::TileKey>* surface_tiles,
                                        ChangedVossels* vossels) {
  const int B = BlockVossels(T);
  const double h = now.vossel_size_m;
  std::map<tiles::TileKey, ChangedBlock> blocks;  // keyed by block coordinates
  auto add = [&](const records::VosselGeometry& g, size_t v) {
    const tiles::TileKey b = tiles::TileOf(g.coord[v], B);
    auto [it, fresh] = blocks.try_emplace(b);
    ChangedBlock& block = it->second;
    // The box of the block's changed cells alone: a change at one corner of a block is not
    // taken as seen from wherever the block's far corner is.
    const tiles::Box cell = tiles::BoxOf(tiles::TileOf(g.coord[v], 1), 1, h);
    if (fresh) {
      block.key = b;
      block.tile = tiles::TileOf(g.coord[v], T);
      block.box = cell;
    } else {
      block.box.min_m = block.box.min_m.cwiseMin(cell.min_m);
      block.box.max_m = block.box.max_m.cwiseMax(cell.max_m);
    }
    block.centroid_m.push_back(g.FrameCentroid(v).cast<double>());
    block.normal.push_back(g.FrameNormal(v).cast<double>());
    surface_tiles->insert(block.tile);
  };
  const bool frames = !old.frame.empty() && !now.frame.empty();
  std::vector<int32_t> new_to_old(now.size(), -1);
  std::vector<uint8_t> old_changed(old.size(), 0), new_changed(now.size(), 0);
  for (size_t v = 0; v < old_to_new.size(); ++v) {
    const int32_t n = old_to_new[v];
    if (n < 0) {
      add(old, v);
      old_changed[v] = 1;
      continue;
    }
    new_to_old[size_t(n)] = int32_t(v);
    const bool surface = old.point_count[v] != now.point_count[size_t(n)] ||
                         old.centroid_m[v] != now.centroid_m[size_t(n)] ||
                         old.normal[v] != now.normal[size_t(n)];
    if (frames ? old.frame[v] != now.frame[size_t(n)] : surface) {
      add(old, v);
      add(now, size_t(n));
      old_changed[v] = new_changed[size_t(n)] = 1;
    } else if (surface) {
      surface_tiles->insert(tiles::TileOf(now.coord[size_t(n)], T));
    }
  }
  for (size_t n = 0; n < now.size(); ++n) {
    if (new_to_old[n] < 0) {
      add(now, n);
      new_changed[n] = 1;
    }
  }
  if (vossels != nullptr) {
    vossels->old_splats.vossel_size_m = h;
    for (size_t v = 0; v < old.size(); ++v) {
      if (!old_changed[v]) continue;
      vossels->old_splats.coord.push_back(old.coord[v]);
      vossels->old_splats.centroid_m.push_back(old.FrameCentroid(v));
      vossels->old_splats.normal.push_back(old.FrameNormal(v));
    }
    vossels->new_to_old = std::move(new_to_old);
    vossels->changed_new = std::move(new_changed);
  }
  std::vector<ChangedBlock> out;
  out.reserve(blocks.size());
  for (auto& [key, block] : blocks) out.push_back(std::move(block));
  return out;
}

std::set<tiles::TileKey> AffectedBlocks(const SourceRef& source, const tiles::ReachRaster* reach,
                                        const std::vector<ChangedBlock>& changed,
                                        const std::set<tiles::TileKey>& all, int B, double h) {
  const Eigen::Vector3d o = source.info.pose.o_world;
  const double grow_m = 2.0 * h;
  const double margin_rad = AngularMarginRad(source);
  const double pixel_rad = TolerancePixelRad(source);
  const double tau_m = ingest::DepthToleranceM(h);
  auto widen = [&](tiles::ViewCap cap) {
    cap.half_angle_rad += margin_rad;
    return cap;
  };
  // 1. Changed blocks the source may reach (see change.h), by the box of their changed cells.
  std::vector<tiles::ViewCap> reached;
  std::set<tiles::TileKey> out;
  for (const ChangedBlock& c : changed) {
    const tiles::ViewCap cap = widen(tiles::CapOf(c.box, o, grow_m));
    double min_depth = cap.near_m - grow_m;
    for (size_t k = 0; k < c.centroid_m.size(); ++k) {
      const Eigen::Vector3d to_sensor = o - c.centroid_m[k];
      const double r = to_sensor.norm();
      const double cos_inc =
          c.normal[k].squaredNorm() < 0.5 ? 1.0 : std::abs(c.normal[k].dot(to_sensor)) / std::max(r, 1e-9);
      min_depth = std::min(min_depth, r - h - ingest::SlopeScaledToleranceM(tau_m, r, pixel_rad, cos_inc));
    }
    if (reach != nullptr && !tiles::Reaches(*reach, source.info.pose, cap, min_depth)) continue;
    reached.push_back(cap);
    out.insert(c.key);
  }
  if (reached.empty()) return out;
  // 2. Blocks whose view from the source passes through a reachable changed block.
  for (const tiles::TileKey& t : all) {
    if (out.count(t)) continue;
    const tiles::ViewCap cap = widen(tiles::CapOf(tiles::BoxOf(t, B, h), o, grow_m));
    for (const tiles::ViewCap& c : reached) {
      if (cap.far_m + 2.0 * grow_m >= c.near_m && tiles::CapsOverlap(cap, c, 0.0)) {
        out.insert(t);
        break;
      }
    }
  }
  return out;
}

RevisitScope ScopeOf(const SourceRef& source, const records::VosselGeometry& g,
                     const std::vector<uint8_t>& candidates,
                     const std::vector<uint8_t>& changed_new, const ChangedSplats& changes,
                     const std::vector<tiles::TileKey>& blocks,
                     const std::vector<int32_t>& block_of, int B,
                     const tiles::ReachRaster* reach) {
  const double h = g.vossel_size_m;
  const Eigen::Vector3d o = source.info.pose.o_world;
  const double grow_m = 2.0 * h;
  const double margin_rad = AngularMarginRad(source);
  // A camera's tests read the dilated panorama: its pixels take the min over a window, so a
  // test reads that much farther out (one pixel more for rounding).
  const double dilation_rad =
      source.returns() ? 0.0 : (ingest::CameraSampleRadiusPx() + 1.0) * DepthPixelRad(source);
  const double spread_rad = std::max(
      {source.info.divergence_rad, DepthPixelRad(source),
       source.returns() || source.info.width_px <= 0
           ? 0.0
           : ingest::ProjectionOf(CameraOf(source.info, 0), source.info.width_px,
                                  source.info.height_px)
                 .AxisPixelAngleRad()});
  const ingest::DepthView view = ViewOf(source);
  const tiles::CapCells grid({view.size.width_px / tiles::kReachBlockPx,
                              view.size.height_px / tiles::kReachBlockPx},
                             source.info.pose);
  const double sphere_m = 0.5 * std::sqrt(3.0) * h;  // a vossel's bounding sphere (§5)
  // A cap about the direction to `x`, of the angle a sphere of `radius_m` there subtends,
  // widened by `widen_rad`; its far side: the range of x plus `depth_m`.
  auto cap_about = [&o](const Eigen::Vector3d& x, double radius_m, double widen_rad,
                        double depth_m) {
    tiles::ViewCap cap;
    const Eigen::Vector3d to = x - o;
    const double r = to.norm();
    cap.near_m = std::max(0.0, r - depth_m);
    cap.far_m = r + depth_m;
    if (r <= radius_m) {
      cap.everywhere = true;
      cap.half_angle_rad = M_PI;
      return cap;
    }
    cap.dir = to / r;
    cap.half_angle_rad = std::asin(radius_m / r) + widen_rad;
    return cap;
  };
  constexpr double kPatchM = ingest::kSamplePatchM;  // × h: the reach of a vossel's tests
  std::vector<float> far(grid.cell_count(), 0.0f);  // per cell: splat exactly to this depth
  auto splat_to = [&](const tiles::ViewCap& cap) {
    const float far_m = float(cap.far_m);
    grid.ForEach(cap, [&](size_t cell, bool) {
      far[cell] = std::max(far[cell], far_m);
      return true;
    });
  };

  // 1. The vossels recomputed: the changed ones, and those with a test sample where a changed
  //    splat, old or new, lies nearer than the sample's threshold. D before and after the
  //    change are min(D_rest, S_old) and min(D_rest, S_new) (a camera's dilated: the min over
  //    a window commutes with them); where min(S_old, S_new) ≥ the threshold both tests read
  //    D_rest, so every other test, and with it the vossel's records, is as it was.
  RevisitScope scope;
  scope.only.assign(g.size(), 0);
  std::vector<uint8_t> unchanged(g.size(), 0);
  for (size_t k = 0; k < g.size(); ++k) {
    scope.only[k] = candidates[k] && changed_new[k];
    unchanged[k] = candidates[k] && !changed_new[k];
  }
  if (changes.splats.size() > 0) {
    ingest::DepthPanorama s = ingest::RenderDepthPanorama(changes.splats, source.info.pose,
                                                          view.size, view.divergence_rad);
    // The rows the splats reach (+inf stays +inf elsewhere, dilated or not).
    const int H = view.size.height_px;
    const bool reached = s.splat_row_begin < std::min(s.splat_row_end, H);
    const int first = s.splat_row_begin - view.dilate_px;
    const int end = std::min(s.splat_row_end, H) + view.dilate_px;
    if (view.dilate_px > 0 && reached) ingest::DilateDepthPanorama(s, view.dilate_px, first, end);
    // Tested sample by sample only where S may lie nearer than the vossel's farthest sample
    // in a reach cell its tests can read (S's min per cell, over ingest::SampleCap).
    const std::vector<float> cell_min =
        tiles::CellMinFromDepth(s.depth_m, view.size, first, reached ? end : first);
    const double pitch_rad =
        std::max(geometry::AzimuthPitchRad(view.size), geometry::ElevationPitchRad(view.size));
    const double patch_m = ingest::kSamplePatchM * h;
    const Eigen::Matrix3d R_sensor_world =
        source.info.pose.q_world_sensor.conjugate().toRotationMatrix();
    const double tau_m = ingest::DepthToleranceM(h);
    const double slope_rad = view.slope_pixels * pitch_rad;  // as ComputeVisibility's
    // Whole runs of kChunk consecutive vossels (neighbours in the lattice's order) first: when
    // S lies nowhere nearer than the far side of the cap of their frame centroids' box (grown
    // by the patch, one pixel wider), which holds each one's SampleCap, less τ, none is tested.
    constexpr size_t kChunk = 64;
    auto chunk_behind = [&](size_t begin, size_t end) {
      Eigen::Vector3d lo = Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity());
      Eigen::Vector3d hi = -lo;
      for (size_t k = begin; k != end; ++k) {
        if (!unchanged[k]) continue;
        const Eigen::Vector3d x = g.FrameCentroid(k).cast<double>();
        lo = lo.cwiseMin(x);
        hi = hi.cwiseMax(x);
      }
      if (!(lo.x() <= hi.x())) return true;  // none of them to test
      tiles::ViewCap cap = tiles::CapOf({lo, hi}, o, patch_m);
      if (cap.everywhere || !(cap.near_m > 2.0 * patch_m)) return false;  // test one by one
      cap.half_angle_rad += pitch_rad;
      // A sample lies no farther than the box's far side (CapOf's) and the patch, and its
      // threshold at least the least tolerance τ nearer than that.
      const double threshold_m = cap.far_m + patch_m - tau_m;
      bool nearer = false;
      grid.ForEach(cap, [&](size_t cell, bool) {
        nearer = double(cell_min[cell]) < threshold_m;
        return !nearer;
      });
      return !nearer;
    };
    tbb::parallel_for(tbb::blocked_range<size_t>(0, g.size(), 4096),
                      [&](const tbb::blocked_range<size_t>& r) {
      for (size_t k = r.begin(); k != r.end(); ++k) {
        if (k == r.begin() || k % kChunk == 0) {
          const size_t chunk_end = std::min(r.end(), (k / kChunk + 1) * kChunk);
          if (chunk_behind(k, chunk_end)) {
            std::fill(unchanged.begin() + k, unchanged.begin() + chunk_end, uint8_t{0});
            k = chunk_end - 1;  // S lies behind every test of the run
            continue;
          }
        }
        if (!unchanged[k]) continue;
        const std::optional<tiles::ViewCap> cap =
            ingest::SampleCap(g.FrameCentroid(k).cast<double>(), o, h, pitch_rad);
        if (!cap) continue;  // at the sensor: test it
        // Every sample's threshold (ComputeVisibility's: its range, no more than the cap's far
        // side, less the vossel's tolerance) lies no deeper than this.
        const double threshold_m =
            cap->far_m - ingest::VosselToleranceM(tau_m, o - g.FrameCentroid(k).cast<double>(),
                                                  g.FrameNormal(k).cast<double>(), slope_rad);
        bool nearer = false;  // S may lie nearer than that in a cell the samples read
        grid.ForEach(*cap, [&](size_t cell, bool) {
          nearer = double(cell_min[cell]) < threshold_m;
          return !nearer;
        });
        // Then pixel by pixel: over the pixels the cap's directions fall in (a sample reads
        // the pixel its direction falls in, and the cap holds every sample's direction).
        if (nearer) {
          nearer = NearerInCap(s, R_sensor_world * cap->dir, cap->half_angle_rad, threshold_m);
        }
        if (!nearer) unchanged[k] = 0;  // S lies behind every test
      }
    });
    const std::vector<float> lit =
        ingest::ComputeVisibility(g, s, tau_m, &unchanged, view.slope_pixels,
                                  /*shadow_by_cells=*/false);
    for (size_t k = 0; k < g.size(); ++k) {
      if (unchanged[k] && lit[k] < 1.0f) scope.only[k] = 1;
    }
  }

  // 2. The cells splatted exactly: those the recomputed tests read (a changed vossel's by its
  //    whole cell, its old frame's samples being read too), to their farthest range; and those
  //    an old splat left, whose reach the revisit recomputes, to the splat's far side.
  for (size_t k = 0; k < g.size(); ++k) {
    if (!scope.only[k]) continue;
    const openvdb::Coord& c = g.coord[k];
    splat_to(changed_new[k]
                 ? cap_about(h * Eigen::Vector3d(c.x(), c.y(), c.z()), sphere_m + kPatchM * h,
                             margin_rad + dilation_rad, sphere_m + kPatchM * h)
                 : cap_about(g.FrameCentroid(k).cast<double>(), kPatchM * h,
                             margin_rad + dilation_rad, kPatchM * h));
  }
  // An old splat nearer nowhere than the old reach there lay behind the old depth wherever it
  // fell: leaving changes no depth, nor the reach. (A LiDAR's reach bounds its depth pixel by
  // pixel; a camera's is binned from its dilated depth, which bounds the depth of no pixel.)
  const bool bounded = source.returns() && reach != nullptr &&
                       reach->size.width_px == grid.size().width_px &&
                       reach->size.height_px == grid.size().height_px;
  for (size_t v = 0; v < changes.before; ++v) {
    // The splat of cell c falls within the angle of its bounding sphere grown by σ(r), at
    // depths within the cube of half-edge h/2 + σ about its centre (RenderDepthPanorama).
    const openvdb::Coord& c = changes.splats.coord[v];
    const Eigen::Vector3d centre = h * Eigen::Vector3d(c.x(), c.y(), c.z());
    const double sigma_m = geometry::SpotSigmaM((centre - o).norm() + sphere_m, spread_rad);
    const tiles::ViewCap cap =
        cap_about(centre, sphere_m + sigma_m, margin_rad, std::sqrt(3.0) * (0.5 * h + sigma_m));
    if (!bounded || grid.Reaches(cap, reach->max_depth_m, cap.near_m)) splat_to(cap);
  }

  // 3. The context: blocks whose splats can fall in a splatted cell nearer than its far depth.
  std::vector<uint8_t> in_context(blocks.size(), 0);
  tbb::parallel_for(size_t(0), blocks.size(), [&](size_t b) {
    tiles::ViewCap cap = tiles::CapOf(tiles::BoxOf(blocks[b], B, h), o, grow_m);
    cap.half_angle_rad += margin_rad;
    const double near =
        cap.near_m - grow_m - std::sqrt(3.0) * geometry::SpotSigmaM(cap.far_m, spread_rad);
    grid.ForEach(cap, [&](size_t cell, bool) {
      if (far[cell] > 0.0f && near <= double(far[cell])) in_context[b] = 1;
      return in_context[b] == 0;
    });
  });
  scope.context.resize(g.size());
  for (size_t k = 0; k < g.size(); ++k) scope.context[k] = in_context[size_t(block_of[k])];
  scope.cells.resize(grid.cell_count());
  for (size_t c = 0; c < far.size(); ++c) scope.cells[c] = far[c] > 0.0f ? 2 : 0;
  return scope;
}

absl::StatusOr<ingest::SourceRecords> StoredSourceRecords(
    const store::ProjectStore& store, const SourceRef& source,
    const records::VosselGeometry& geometry, int64_t max_image_pixels,
    const std::vector<uint8_t>* only, const std::vector<uint8_t>* context) {
  if (source.lidar()) {
    absl::StatusOr<ingest::LidarSource> lidar = LoadLidar(store, source.info, source.batch);
    if (!lidar.ok()) return lidar.status();
    return ingest::LidarRecords(geometry, *lidar, only, context);
  }
  if (source.point_colour()) {
    absl::StatusOr<ingest::LidarSource> points = LoadPointColour(store, source.info, source.batch);
    if (!points.ok()) return points.status();
    return ingest::PointColourRecords(geometry, *points, only, context);
  }
  if (source.derived()) {  // §10: its pixels land on vossels again; no depth panorama
    absl::StatusOr<ingest::DerivedSource> derived =
        LoadDerived(store, source.info, source.batch, max_image_pixels);
    if (!derived.ok()) return derived.status();
    ingest::SourceRecords out;
    out.records = ingest::BackProjectRecords(geometry, *derived, only);
    return out;
  }
  return ingest::CameraRecords(
      geometry, StoredCamera(store, source.info, source.batch, max_image_pixels), only, context);
}

ingest::SourceVisibility StoredVisibility(const SourceRef& source,
                                          const records::VosselGeometry& geometry,
                                          const std::vector<uint8_t>* only,
                                          const std::vector<uint8_t>* context,
                                          const std::vector<uint8_t>* read_cells) {
  if (source.returns()) {
    return ingest::LidarVisibility(geometry, source.info.pose, ViewOf(source), only, context,
                                   read_cells);
  }
  return ingest::CameraVisibility(geometry, CameraOf(source.info, source.batch),
                                  source.info.width_px, source.info.height_px, only, context,
                                  read_cells);
}

absl::StatusOr<ingest::SourceRecords> StoredSourceRecords(const store::ProjectStore& store,
                                                          const SourceRef& source,
                                                          const records::VosselGeometry& geometry,
                                                          int64_t max_image_pixels,
                                                          ingest::SourceVisibility visibility,
                                                          SourceImageCache* images) {
  if (source.lidar()) {  // through the kept LiDARs, as cameras below
    absl::StatusOr<std::shared_ptr<const ingest::LidarSource>> lidar =
        LoadedLidar(store, source.info, source.batch, images);
    if (!lidar.ok()) return lidar.status();
    return ingest::LidarRecords(geometry, **lidar, std::move(visibility));
  }
  if (source.point_colour()) {
    absl::StatusOr<ingest::LidarSource> points = LoadPointColour(store, source.info, source.batch);
    if (!points.ok()) return points.status();
    return ingest::PointColourRecords(geometry, *points, std::move(visibility));
  }
  if (source.derived()) {
    return absl::InternalError("StoredSourceRecords: a derived source has no visibility");
  }
  // A revisit's: through the decoded cameras, which the next ingest's revisits mostly read
  // again.
  absl::StatusOr<ingest::CameraSource> cam =
      LoadedCamera(store, source.info, source.batch, max_image_pixels, images);
  if (!cam.ok()) return cam.status();
  return ingest::CameraRecords(geometry, *cam, std::move(visibility));
}

std::optional<records::RecordSet> RefreshedRecords(const SourceRef& source,
                                                   records::RecordSet before,
                                                   const records::VosselGeometry& old_geometry,
                                                   const records::VosselGeometry& geometry,
                                                   const ChangedVossels& changed,
                                                   const std::vector<uint8_t>& only,
                                                   const ingest::SourceVisibility& visibility) {
  const bool returns = source.returns();
  std::vector<uint8_t> recorded(geometry.size(), 0);
  std::vector<size_t> keep;
  keep.reserve(before.size());
  for (size_t i = 0; i < before.size(); ++i) {
    const size_t k = size_t(before.vossel[i]);
    recorded[k] = 1;
    const float vis = visibility.vis[k];
    if (!(vis > 0.0f)) continue;  // turned to shadow
    if (changed.changed_new[k]) {
      // A camera samples its image where the new frame projects; returns keep their values.
      if (!returns) return std::nullopt;
      ingest::ReturnTerms t;
      if (!ingest::ReturnTermsOf(geometry, k, source.info.pose, source.info.divergence_rad,
                                 visibility.depth.size, &t)) {
        continue;
      }
      before.range_m[i] = float(t.range_m);
      before.cos_inc[i] = float(t.cos_inc);
      before.foot_major_m[i] = float(t.foot.major_m);
      before.foot_minor_m[i] = float(t.foot.minor_m);
      before.uv_px[2 * i] = float(t.uv.x());
      before.uv_px[2 * i + 1] = float(t.uv.y());
    }
    before.vis[i] = vis;
    keep.push_back(i);
  }
  // Seen now and not recorded before: a record may begin here, from the source's points or
  // pixels; except where the source was sure to record nothing: an older LiDAR has no return
  // in a vossel that appeared after it, and a vossel seen before too was left unrecorded for
  // good (an unchanged one: no return of the LiDAR in it, or outside the photo; one whose frame
  // changed: no return of the LiDAR in it). With D_rest the depth of the vossels the change
  // left alone (D_now = min(D_rest, S_new) ≥ its new threshold at a lit sample, D_before =
  // min(D_rest, S_old) with S_old the changed vossels' old splats):
  //   - an unchanged vossel was seen before when S_old lies behind all its samples, since a
  //     sample lit now has D_rest ≥ its threshold, and D_before was then too;
  //   - a reframed vossel was seen before when some sample of its old frame lies nearer than
  //     min(D_now, S_old) ≤ D_before (the revisit's D_now is exact on its blocks).
  std::vector<uint8_t> unrecorded(geometry.size(), 0), reframed(old_geometry.size(), 0);
  bool any_unrecorded = false, any_reframed = false;
  for (size_t k = 0; k < geometry.size(); ++k) {
    if (!only[k] || recorded[k] || !(visibility.vis[k] > 0.0f)) continue;
    const bool appeared = changed.new_to_old[k] < 0;
    if (returns && appeared) continue;
    if (!changed.changed_new[k]) {
      unrecorded[k] = 1;
      any_unrecorded = true;
    } else if (returns && !appeared) {
      reframed[size_t(changed.new_to_old[k])] = 1;
      any_reframed = true;
    } else {
      return std::nullopt;
    }
  }
  if ((any_unrecorded || any_reframed) && changed.old_splats.size() > 0) {
    const ingest::DepthView view = ViewOf(source);
    const double tau_m = ingest::DepthToleranceM(geometry.vossel_size_m);
    ingest::DepthPanorama s_old = ingest::RenderDepthPanorama(
        changed.old_splats, source.info.pose, view.size, view.divergence_rad);
    ingest::DilateDepthPanorama(s_old, view.dilate_px);
    if (any_unrecorded) {
      const std::vector<float> lit =
          ingest::ComputeVisibility(geometry, s_old, tau_m, &unrecorded, view.slope_pixels,
                                    /*shadow_by_cells=*/false);
      for (size_t k = 0; k < geometry.size(); ++k) {
        if (unrecorded[k] && lit[k] < 1.0f) return std::nullopt;
      }
    }
    if (any_reframed) {  // a LiDAR's: its panorama is not dilated
      for (size_t p = 0; p < s_old.depth_m.size(); ++p) {
        s_old.depth_m[p] = std::min(s_old.depth_m[p], visibility.depth.depth_m[p]);
      }
      const std::vector<float> lit =
          ingest::ComputeVisibility(old_geometry, s_old, tau_m, &reframed, view.slope_pixels);
      for (size_t v = 0; v < old_geometry.size(); ++v) {
        if (reframed[v] && !(lit[v] > 0.0f)) return std::nullopt;
      }
    }
  }  // (a reframed vossel has an old splat: with none, nothing is to check)
  records::RecordSet out = before.Select(keep);
  records::RoundToStorage(out);
  return out;
}

namespace {

/// Sources revisited at once: each holds its decoded image or points while it is computed.
constexpr int kMaxConcurrentRevisits = 4;
/// Bytes of decoded images revisits may hold at once: fewer sources run together when their
/// images are large (one at a time from 8192×4096 up, which decode to 400 MB each).
constexpr int64_t kRevisitImageBytes = int64_t{512} << 20;

// The blocks of a geometry numbered densely (in key order), and each vossel's number: a set of
// blocks is then a table by number, and a vossel is looked up in it without a set search.
struct BlockNumbers {
  std::vector<tiles::TileKey> numbered;
  std::vector<int32_t> of_vossel;

  BlockNumbers(const std::vector<tiles::TileKey>& block_of,
               const std::set<tiles::TileKey>& all_blocks)
      : numbered(all_blocks.begin(), all_blocks.end()), of_vossel(block_of.size()) {
    tbb::parallel_for(size_t(0), block_of.size(), [&](size_t v) {
      of_vossel[v] = int32_t(std::lower_bound(numbered.begin(), numbered.end(), block_of[v]) -
                             numbered.begin());
    });
  }
  // 1 for the blocks of `blocks` (a subset of the numbered ones), by number.
  std::vector<uint8_t> Table(const std::set<tiles::TileKey>& blocks) const {
    std::vector<uint8_t> in(numbered.size(), 0);
    auto b = blocks.begin();
    for (size_t n = 0; n < numbered.size(); ++n) {
      while (b != blocks.end() && *b < numbered[n]) ++b;
      if (b != blocks.end() && *b == numbered[n]) in[n] = 1;
    }
    return in;
  }
};

// The records `rows` of `records`, their vossels renumbered into the new geometry (room for
// `capacity` records).
records::RecordSet Renumbered(const records::RecordSet& records, const std::vector<size_t>& rows,
                              const std::vector<int32_t>& old_to_new, size_t capacity = 0) {
  records::RecordSet out = records.Select(rows, capacity);
  for (int32_t& v : out.vossel) v = old_to_new[size_t(v)];
  return out;
}

/// Step 4 of Propagate: finds each revisited source's visibility on its blocks, refreshes its
/// records from themselves where that is exact (RefreshedRecords) or recomputes them from its
/// blob, and merges them and its reach raster into `next`. Sources run concurrently (at most
/// kMaxConcurrentRevisits, no more than the threads, and within kRevisitImageBytes of decoded
/// images) and merge in source-id order, so the result does not depend on which finishes
/// first. `records_of`: per revisited source, the rows of `old_records` on its blocks' vossels
/// that stay.
absl::Status RevisitSources(const store::ProjectStore& store, const store::Snapshot& old,
                            const records::RecordSet& old_records,
                            const records::VosselGeometry& g,
                            const std::map<int32_t, std::set<tiles::TileKey>>& revisit,
                            const ChangedVossels& changed,
                            const std::vector<int32_t>& old_to_new,
                            const std::vector<SourceRef>& old_sources,
                            const BlockNumbers& block_numbers,
                            const std::map<int32_t, std::vector<size_t>>& records_of, int B,
                            int T, int64_t max_image_pixels, SourceImageCache* images,
                            store::Snapshot& next,
                            store::CommitPlan& plan, std::set<tiles::TileKey>& record_tiles,
                            FlowResult& result, StageClock& clock) {
  const std::vector<int32_t>& block_number = block_numbers.of_vossel;
  struct Job {
    const SourceRef* src = nullptr;
    const std::set<tiles::TileKey>* blocks = nullptr;
    std::set<tiles::TileKey> tiles;
    std::vector<uint8_t> cells;  ///< the reach cells its depth panorama splatted exactly
    absl::StatusOr<ingest::SourceRecords> computed;
    records::RecordSet kept;  ///< its records on the blocks' vossels it did not recompute
    int64_t vossels = 0;      ///< the vossels it recomputed
    int64_t candidates = 0;   ///< the vossels of its blocks
    bool refreshed = false;   ///< from its records before the change, without its blob
    bool unchanged = false;   ///< the change alters none of its records, nor its reach
  };
  ChangedSplats changed_splats;
  changed_splats.splats = changed.old_splats;
  changed_splats.before = changed.old_splats.size();
  for (size_t v = 0; v < g.size(); ++v) {
    if (!changed.changed_new[v]) continue;
    changed_splats.splats.coord.push_back(g.coord[v]);
    changed_splats.splats.centroid_m.push_back(g.FrameCentroid(v));
    changed_splats.splats.normal.push_back(g.FrameNormal(v));
  }
  std::vector<const SourceRef*> order;
  for (const SourceRef& src : old_sources) {
    if (revisit.count(src.info.id)) order.push_back(&src);
  }
  const double span = 0.3 / double(order.size() + 1);
  size_t next_job = 0;
  absl::Status status;
  int64_t largest_image = 1;
  for (const SourceRef* src : order) {
    largest_image = std::max(largest_image, DecodedImageBytes(src->info));
  }
  const int tokens = int(std::clamp<int64_t>(
      std::min<int64_t>(tbb::this_task_arena::max_concurrency(),
                        kRevisitImageBytes / largest_image),
      1, kMaxConcurrentRevisits));
  tbb::parallel_pipeline(
      size_t(tokens),
      tbb::make_filter<void, std::shared_ptr<Job>>(
          tbb::filter_mode::serial_in_order,
          [&](tbb::flow_control& fc) -> std::shared_ptr<Job> {
            if (next_job == order.size() || !status.ok()) {
              fc.stop();
              return nullptr;
            }
            auto job = std::make_shared<Job>();
            job->src = order[next_job];
            job->blocks = &revisit.at(job->src->info.id);
            for (const tiles::TileKey& b : *job->blocks) {
              job->tiles.insert(tiles::TileOf(openvdb::Coord(b.x * B, b.y * B, b.z * B), T));
            }
            const std::string stage =
                absl::StrCat("revisit source ", job->src->info.id, " on ", job->blocks->size(),
                             " blocks of ", job->tiles.size(), " tiles");
            if (absl::Status stop = clock.Start(stage, 0.5 + span * double(next_job)); !stop.ok()) {
              status = stop;
              fc.stop();
              return nullptr;
            }
            ++next_job;
            return job;
          }) &
          tbb::make_filter<std::shared_ptr<Job>, std::shared_ptr<Job>>(
              tbb::filter_mode::parallel,
              [&](std::shared_ptr<Job> job) {
                // The vossels of the revisited blocks.
                const SourceRef& src = *job->src;
                const std::vector<uint8_t> in_blocks = block_numbers.Table(*job->blocks);
                std::vector<uint8_t> candidates(g.size(), 0);
                for (size_t v = 0; v < g.size(); ++v) {
                  candidates[v] = in_blocks[size_t(block_number[v])];
                }
                job->candidates = std::count(candidates.begin(), candidates.end(), uint8_t{1});
                auto mine = records_of.find(src.info.id);
                const bool sized =
                    src.returns() || (src.info.width_px > 0 && src.info.height_px > 0);
                if (src.derived() || !sized) {  // no visibility without a size: from the blob
                  job->vossels = job->candidates;
                  job->computed =
                      StoredSourceRecords(store, src, g, max_image_pixels, &candidates, nullptr);
                  return job;
                }
                // Of them, the vossels whose records the change may alter, and the blocks whose
                // splats the depth panorama needs for their tests: it splats those only.
                auto old_reach = old.reach.find(src.info.id);
                RevisitScope scope = ScopeOf(
                    src, g, candidates, changed.changed_new, changed_splats,
                    block_numbers.numbered, block_number, B,
                    old_reach == old.reach.end() ? nullptr : &old_reach->second);
                job->vossels = std::count(scope.only.begin(), scope.only.end(), uint8_t{1});
                job->cells = std::move(scope.cells);
                if (job->vossels == 0 && std::none_of(job->cells.begin(), job->cells.end(),
                                                      [](uint8_t c) { return c != 0; })) {
                  // Nothing of the source changes: its records stay, and its reach too.
                  if (mine != records_of.end()) {
                    job->kept = Renumbered(old_records, mine->second, old_to_new);
                  }
                  job->computed = ingest::SourceRecords{};
                  job->unchanged = true;
                  return job;
                }
                // Visibility first; the blob only when a record needs its points or pixels.
                ingest::SourceVisibility visibility =
                    StoredVisibility(src, g, &scope.only, &scope.context, &job->cells);
                std::vector<size_t> redo, keep;  // its records before on them: recomputed or not
                if (mine != records_of.end()) {
                  for (size_t i : mine->second) {
                    (scope.only[size_t(old_to_new[size_t(old_records.vossel[i])])] ? redo : keep)
                        .push_back(i);
                  }
                }
                job->kept = Renumbered(old_records, keep, old_to_new);
                records::RecordSet before = Renumbered(old_records, redo, old_to_new);
                if (std::optional<records::RecordSet> kept = RefreshedRecords(
                        src, std::move(before), old.geometry, g, changed, scope.only,
                        visibility)) {
                  job->computed = ingest::SourceRecords{std::move(*kept),
                                                        std::move(visibility.reach)};
                  job->refreshed = true;
                  return job;
                }
                job->computed = StoredSourceRecords(store, src, g, max_image_pixels,
                                                    std::move(visibility), images);
                return job;
              }) &
          tbb::make_filter<std::shared_ptr<Job>, void>(
              tbb::filter_mode::serial_in_order, [&](std::shared_ptr<Job> job) {
                if (!status.ok()) return;
                if (!job->computed.ok()) {
                  status = job->computed.status();
                  return;
                }
                const SourceRef& src = *job->src;
                ingest::SourceRecords& recs = *job->computed;
                next.records.Append(recs.records);
                next.records.Append(job->kept);
                result.records_computed += int64_t(recs.records.size());
                result.vossels_revisited += job->vossels;
                result.vossels_in_blocks += job->candidates;
                record_tiles.insert(job->tiles.begin(), job->tiles.end());
                ++result.sources_revisited;
                if (job->refreshed) ++result.sources_refreshed;
                result.pairs_revisited += int64_t(job->tiles.size());
                result.blocks_revisited += int64_t(job->blocks->size());
                if (src.derived() || job->unchanged) return;  // its reach stays as it was
                auto before = old.reach.find(src.info.id);
                if (before != old.reach.end() &&
                    before->second.size.width_px == recs.reach.size.width_px &&
                    before->second.size.height_px == recs.reach.size.height_px) {
                  recs.reach = tiles::MergeReach(before->second, recs.reach, job->cells);
                }
                next.reach[src.info.id] = std::move(recs.reach);
                plan.reach_sources.insert(src.info.id);
              }));
  return status;
}

}  // namespace

absl::StatusOr<store::Snapshot> Propagate(const store::ProjectStore& store,
                                          const store::Snapshot& old, Change change,
                                          const std::vector<SourceRef>& old_sources,
                                          int64_t max_image_pixels, SourceImageCache* images,
                                          store::CommitPlan& plan, FlowResult& result,
                                          StageClock& clock) {
  const int T = old.tile_vossels;
  const double h = change.geometry.vossel_size_m;
  store::Snapshot next;
  next.tile_vossels = T;
  next.geometry = std::move(change.geometry);
  const records::VosselGeometry& g = next.geometry;
  const int B = BlockVossels(T);
  const std::vector<tiles::TileKey> tile_of = tiles::TilesOfVossels(g, T);
  const std::vector<tiles::TileKey> block_of = tiles::TilesOfVossels(g, B);
  std::set<tiles::TileKey> all_blocks;  // (vossels in lattice order: a block's come in runs)
  for (size_t v = 0; v < block_of.size(); ++v) {
    if (v == 0 || block_of[v] != block_of[v - 1]) all_blocks.insert(all_blocks.end(), block_of[v]);
  }
  auto tile_of_block = [B, T](const tiles::TileKey& b) {
    return tiles::TileOf(openvdb::Coord(b.x * B, b.y * B, b.z * B), T);
  };

  // 1. Changed blocks: vossels that appeared, vanished, or whose record frame changed; and the
  //    tiles whose surface (count, centroid, normal) changed, whose geometry is rewritten.
  if (absl::Status stop = clock.Start("find changes", 0.45); !stop.ok()) return stop;
  ChangedVossels changed;
  const std::vector<ChangedBlock> blocks =
      ChangedBlocks(old.geometry, g, change.old_to_new, T, &plan.geometry_tiles, &changed);

  std::set<tiles::TileKey> record_tiles;  // tiles whose records change

  // 2. Which older sources must be recomputed on which blocks.
  std::map<int32_t, std::set<tiles::TileKey>> revisit;  // source → blocks
  for (const SourceRef& src : old_sources) {
    if (src.derived()) {
      // A derived source's records depend on which vossels exist where its pixels land and on
      // their normals: exactly the changed blocks.
      std::set<tiles::TileKey> changed;
      for (const ChangedBlock& b : blocks) {
        if (all_blocks.count(b.key)) changed.insert(b.key);
      }
      if (!changed.empty()) revisit[src.info.id] = std::move(changed);
      continue;
    }
    // A raster binned from a panorama of another size (stored before depth panoramas were
    // whole reach cells) bounds nothing here: every changed block is then taken as reached.
    auto it = old.reach.find(src.info.id);
    bool usable = it != old.reach.end();
    if (usable && (src.returns() || (src.info.width_px > 0 && src.info.height_px > 0))) {
      const geometry::EquirectSize pixels = ViewOf(src).size;
      usable = it->second.size.width_px * tiles::kReachBlockPx == pixels.width_px &&
               it->second.size.height_px * tiles::kReachBlockPx == pixels.height_px;
    }
    std::set<tiles::TileKey> blocks_of_src =
        AffectedBlocks(src, usable ? &it->second : nullptr, blocks, all_blocks, B, h);
    if (src.returns() && !blocks_of_src.empty()) {
      absl::StatusOr<std::set<tiles::TileKey>> returns = store.SourceTiles(src.info.id);
      if (!returns.ok()) return returns.status();
      for (auto b = blocks_of_src.begin(); b != blocks_of_src.end();) {
        b = returns->count(tile_of_block(*b)) ? std::next(b) : blocks_of_src.erase(b);
      }
    }
    if (!blocks_of_src.empty()) revisit[src.info.id] = std::move(blocks_of_src);
  }

  // 5. The new sources, on every tile (first: they read the new geometry alone, and their
  //    records say which tiles an ingest within a memory budget reads the old records of).
  records::RecordSet fresh;
  const double fraction = 0.8 - 0.3 / double(revisit.size() + 1);
  auto add_new = [&](ingest::SourceRecords recs, int32_t id) {
    for (int32_t v : recs.records.vossel) record_tiles.insert(tile_of[size_t(v)]);
    fresh.Append(recs.records);
    next.reach[id] = std::move(recs.reach);
    plan.reach_sources.insert(id);
    ++result.sources_computed;
  };
  for (const ingest::LidarSource& lidar : change.new_sources.lidars) {
    if (absl::Status stop = clock.Start(absl::StrCat("records of source ", lidar.id), fraction);
        !stop.ok()) {
      return stop;
    }
    add_new(ingest::LidarRecords(g, lidar), lidar.id);
  }
  for (const ingest::LidarSource& colour : change.new_sources.point_colours) {
    if (absl::Status stop = clock.Start(absl::StrCat("records of source ", colour.colour_id), fraction);
        !stop.ok()) {
      return stop;
    }
    add_new(ingest::PointColourRecords(g, colour), colour.colour_id);
  }
  for (const ingest::DerivedSource& d : change.new_sources.derived) {
    if (absl::Status stop = clock.Start(absl::StrCat("back-project source ", d.id), fraction);
        !stop.ok()) {
      return stop;
    }
    ingest::BackProjectStats stats;
    records::RecordSet recs = ingest::BackProjectRecords(g, d, nullptr, &stats);
    for (int32_t v : recs.vossel) record_tiles.insert(tile_of[size_t(v)]);
    fresh.Append(recs);
    ++result.sources_computed;
    result.pixels_back_projected += stats.pixels_used;
    result.pixels_outside += stats.pixels_outside;
    result.pixels_invalid += stats.pixels_invalid;
  }
  for (ingest::CameraSource& cam : change.new_sources.cameras) {
    if (absl::Status stop = clock.Start(absl::StrCat("records of source ", cam.id), fraction);
        !stop.ok()) {
      return stop;
    }
    absl::StatusOr<ingest::SourceRecords> r = ingest::CameraRecords(g, cam);
    // CameraRecords decoded the panorama and freed it, or read the one the calibration check
    // kept with the camera: freed here (a shared one stays while the revisit cache keeps it).
    ingest::LinearImage().pixels.swap(cam.image.pixels);
    std::vector<float>().swap(cam.image.alpha);
    cam.kept_image.reset();
    cam.artefacts.reset();
    if (!r.ok()) return r.status();
    add_new(std::move(*r), cam.id);
  }
  // The old records this change reads: all of them, or (a HEAD loaded without records, an
  // ingest within a memory budget) those of the tiles it rewrites: the tiles whose geometry
  // changed, those of revisited blocks and those the new sources record on. Every other tile
  // keeps its objects, and the new snapshot holds those tiles' records alone.
  records::RecordSet loaded_records;
  const records::RecordSet* old_records = &old.records;
  if (!old.records_loaded && old.version > 0) {
    std::set<tiles::TileKey> rewritten = plan.geometry_tiles;
    if (!change.dropped_sources.empty()) {  // a deletion: the tiles its sources recorded on
      if (absl::Status stop = clock.Start("find the deleted sources' tiles", 0.48); !stop.ok()) {
        return stop;
      }
      absl::StatusOr<std::set<tiles::TileKey>> holding =
          store.TilesWithRecordsOf(old.version, change.dropped_sources);
      if (!holding.ok()) return holding.status();
      rewritten.insert(holding->begin(), holding->end());
    }
    rewritten.insert(record_tiles.begin(), record_tiles.end());
    for (const auto& [source, blocks] : revisit) {
      for (const tiles::TileKey& b : blocks) rewritten.insert(tile_of_block(b));
    }
    size_t stored = 0;  // of them, the tiles the old version has
    for (const tiles::TileKey& key : rewritten) stored += old.manifest.tiles.count(key);
    if (absl::Status stop = clock.Start(absl::StrCat("read records of ", stored, " of ",
                                                     old.manifest.tiles.size(), " tiles"),
                                        0.5);
        !stop.ok()) {
      return stop;
    }
    absl::StatusOr<records::RecordSet> part =
        store.LoadRecords(old.version, rewritten, old.geometry);
    if (!part.ok()) return part.status();
    loaded_records = std::move(*part);
    old_records = &loaded_records;
    next.records_partial = true;
  }

  // 3. Records carried over: renumbered; a dropped source's, and revisited pairs', left out
  //    (those go, per source, to its revisit). One parallel pass classes them, by tables per
  //    source id and block number.
  const BlockNumbers block_numbers(block_of, all_blocks);
  std::map<int32_t, std::vector<size_t>> revisited_records;  // source → its records on its blocks
  std::vector<size_t> keep;  // the rows of *old_records carried over as they are
  {
    const records::RecordSet& before = *old_records;
    int32_t ids = 0;
    for (int32_t scan : before.scan) ids = std::max(ids, scan + 1);
    std::vector<uint8_t> dropped(size_t(ids), 0);
    for (int32_t id : change.dropped_sources) {
      if (id >= 0 && id < ids) dropped[size_t(id)] = 1;
    }
    std::vector<std::vector<uint8_t>> tables(static_cast<size_t>(ids));  // empty: not revisited
    for (const auto& [id, blocks] : revisit) {
      if (id >= 0 && id < ids) tables[size_t(id)] = block_numbers.Table(blocks);
    }
    enum Class : uint8_t { kKeep, kDropped, kVanished, kRevisited };
    std::vector<uint8_t> klass(before.size());
    tbb::parallel_for(tbb::blocked_range<size_t>(0, before.size(), 1 << 14),
                      [&](const tbb::blocked_range<size_t>& r) {
      for (size_t i = r.begin(); i != r.end(); ++i) {
        const int32_t id = before.scan[i];
        const int32_t n = change.old_to_new[size_t(before.vossel[i])];
        const bool known = id >= 0;  // a source id (ids start at 1)
        klass[i] = known && dropped[size_t(id)] ? kDropped
                   : n < 0                      ? kVanished
                   : known && !tables[size_t(id)].empty() &&
                           tables[size_t(id)][size_t(block_numbers.of_vossel[size_t(n)])]
                       ? kRevisited
                       : kKeep;
      }
    });
    keep.reserve(before.size());
    for (size_t i = 0; i < before.size(); ++i) {
      switch (klass[i]) {
        case kKeep: keep.push_back(i); break;
        case kDropped:
          record_tiles.insert(tiles::TileOf(old.geometry.coord[size_t(before.vossel[i])], T));
          break;
        case kRevisited: revisited_records[before.scan[i]].push_back(i); break;
        default: break;  // its vossel vanished (its tile is a changed one)
      }
    }
  }
  // next.records gathers the records the revisits and the new sources make; the kept ones
  // join them at the end, each copied once (records::MergeRenumbered).
  for (const auto& [source, raster] : old.reach) {
    if (!change.dropped_sources.count(source)) next.reach[source] = raster;
  }
  plan.drop_reach = change.dropped_sources;

  // 4. Recompute the revisited pairs, from the sources' blobs: a few sources at a time (each
  //    one's decode and point loading are mostly serial), merged in source order.
  if (absl::Status s = RevisitSources(store, old, *old_records, g, revisit, changed,
                                      change.old_to_new,
                                      old_sources, block_numbers, revisited_records, B, T,
                                      max_image_pixels, images,
                                      next, plan,
                                      record_tiles, result, clock);
      !s.ok()) {
    return s;
  }

  if (absl::Status stop = clock.Start("merge records", 0.84); !stop.ok()) return stop;
  next.records.Append(fresh);  // 5.
  next.records = records::MergeRenumbered(*old_records, keep, change.old_to_new,
                                          std::move(next.records));
  result.records_computed += int64_t(fresh.size());
  {
    std::vector<uint8_t> rewritten(g.size(), 0);  // per vossel: its tile is rewritten
    for (size_t v = 0; v < g.size(); ++v) {  // (a tile's vossels come in runs: looked up once)
      rewritten[v] = v > 0 && tile_of[v] == tile_of[v - 1]
                         ? rewritten[v - 1]
                         : record_tiles.count(tile_of[v]) || plan.geometry_tiles.count(tile_of[v]);
    }
    for (int32_t v : next.records.vossel) result.records_rewritten += rewritten[size_t(v)];
  }

  // 6. Fusion (§7) under the default profile; per vossel, so the tiles that kept their records
  //    keep their fused values.
  if (absl::Status stop = clock.Start("fuse", 0.85); !stop.ok()) return stop;
  if (absl::Status s = FuseAll(store, old.manifest, next); !s.ok()) return s;
  plan.record_tiles = std::move(record_tiles);
  return next;
}

absl::Status FuseAll(const store::ProjectStore& store, const store::Manifest& head,
                     store::Snapshot& next) {
  const size_t n = next.geometry.size();
  const double h = next.geometry.vossel_size_m;
  absl::StatusOr<records::FusedValues> fused = fusion::Fuse(next.records, n, h, fusion::WeightingProfile{});
  if (!fused.ok()) return fused.status();
  next.fused = std::move(*fused);
  absl::StatusOr<std::vector<fusion::WeightingProfile>> profiles =
      reweight::MaintainedProfiles(store, head);
  if (!profiles.ok()) return profiles.status();
  absl::StatusOr<std::map<std::string, records::FusedValues>> others =
      reweight::FuseProfiles(next.records, n, h, *profiles);
  if (!others.ok()) return others.status();
  next.profile_fused = std::move(*others);
  return absl::OkStatus();
}

absl::Status CommitFlow(store::ProjectStore& store, store::Snapshot next,
                        const store::CommitPlan& plan, FlowResult& result, StageClock& clock) {
  if (absl::Status stop = clock.Start("commit", 0.9); !stop.ok()) return stop;
  absl::StatusOr<int64_t> version = store.Commit(next, plan);
  if (!version.ok()) return version.status();
  next.version = *version;
  absl::StatusOr<store::Manifest> manifest = store.LoadManifest(*version);
  if (!manifest.ok()) return manifest.status();
  next.manifest = std::move(*manifest);
  std::set<tiles::TileKey> written = plan.geometry_tiles;
  written.insert(plan.record_tiles.begin(), plan.record_tiles.end());
  result.tiles_changed = plan.replace_all ? int64_t(next.manifest.tiles.size())
                                          : int64_t(written.size());
  absl::StatusOr<store::VersionInfo> info = store.HeadInfo();
  if (info.ok()) result.bytes_written = info->bytes_written;
  result.commit_times = store.LastCommitTimes();
  result.version = *version;
  // Not a const object: a reweight moves HEAD's arrays out of it when no reader holds it.
  result.snapshot = std::make_shared<store::Snapshot>(std::move(next));
  clock.Finish();
  return absl::OkStatus();
}

}  // namespace vasl::flows::internal

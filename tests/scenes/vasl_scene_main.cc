/// @file vasl_scene_main.cc
/// @brief `vasl_scene`: writes a synthetic site as a capture rig would (per station a LiDAR
///        PLY in the sensor frame, an 8-bit sRGB panorama PNG and a scan manifest), plus the
///        analytic ground truth (linear RGB and range .npy per view) and a scene description.
/// @details Usage:
///   vasl_scene --out DIR [--site room|corridor] [--stations N] [--pano-width W]
///              [--lidar-azimuth-steps A] [--lidar-elevation-steps E] [--supersample S]
///              [--seed K] [--project NAME] [--vossel-size H]
///   --site room (default) is SyntheticRoom::Default() (4 stations, 3 written by default,
///   project "synthetic-room"); --site corridor is CorridorSite::Default() (12 stations, all
///   written by default, project "corridor-site").
///   Files (i = 1-based station index, k = 1-based novel view index):
///     DIR/scan-<i>.ply, DIR/scan-<i>-rgb.png, DIR/scan-<i>.json (manifest, paths relative),
///     DIR/truth/scan-<i>-cam0-{rgb,depth}.npy, DIR/truth/novel-<k>-{rgb,depth}.npy,
///     DIR/truth/views.json, DIR/scene.json.
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "tests/scenes/corridor_site.h"
#include "tests/scenes/synthetic_scene.h"

namespace vasl::scenes {
namespace {

namespace fs = std::filesystem;

/// Which synthetic site to write.
enum class Site { kRoom, kCorridor };

struct Options {
  fs::path out_dir;                  ///< output directory (created)
  Site site = Site::kRoom;           ///< --site room|corridor
  int stations = 3;                  ///< number of stations written (room: 1..4, default 3;
                                     ///< corridor: 1..12, default 12)
  int pano_width_px = 1024;          ///< panorama width; height is width / 2
  int lidar_azimuth_steps = 1440;    ///< 0.25° azimuth pitch
  int lidar_elevation_steps = 720;   ///< 0.25° elevation pitch
  int supersample = 4;               ///< sub-pixel rays per pixel side
  uint64_t seed = 1;                 ///< LiDAR noise seed
  std::string project = "synthetic-room";  ///< project name recorded (corridor: "corridor-site")
  double vossel_size_m = 0.05;       ///< recommended lattice edge, metres (recorded only)
};

constexpr char kUsage[] =
    "usage: vasl_scene --out DIR [--site room|corridor] [--stations N] [--pano-width W]\n"
    "                  [--lidar-azimuth-steps A] [--lidar-elevation-steps E] [--supersample S]\n"
    "                  [--seed K] [--project NAME] [--vossel-size H]\n"
    "  --site room (default): one room with one box, 4 stations (default 3 written)\n"
    "  --site corridor: 4 rooms joined by doors, 12 stations (default all written)\n";

absl::Status ParseArgs(int argc, char** argv, Options* opt) {
  std::map<std::string, std::string> kv;
  for (int a = 1; a < argc; ++a) {
    std::string arg = argv[a];
    if (arg == "-h" || arg == "--help") return absl::CancelledError("help");
    if (arg.rfind("--", 0) != 0) return absl::InvalidArgumentError("unexpected argument " + arg);
    std::string value;
    const size_t eq = arg.find('=');
    if (eq != std::string::npos) {
      value = arg.substr(eq + 1);
      arg = arg.substr(0, eq);
    } else {
      if (a + 1 >= argc) return absl::InvalidArgumentError(arg + " needs a value");
      value = argv[++a];
    }
    kv[arg] = value;
  }
  auto get_int = [&](const std::string& key, int lo, int hi, int* out) -> absl::Status {
    auto it = kv.find(key);
    if (it == kv.end()) return absl::OkStatus();
    int v = 0;
    if (!absl::SimpleAtoi(it->second, &v) || v < lo || v > hi) {
      return absl::InvalidArgumentError(
          absl::StrCat(key, " must be an integer in [", lo, ", ", hi, "], got '", it->second, "'"));
    }
    *out = v;
    kv.erase(it);
    return absl::OkStatus();
  };
  auto it = kv.find("--out");
  if (it == kv.end() || it->second.empty()) {
    return absl::InvalidArgumentError("--out DIR is required");
  }
  opt->out_dir = it->second;
  kv.erase(it);
  if (it = kv.find("--site"); it != kv.end()) {
    if (it->second == "room") {
      opt->site = Site::kRoom;
    } else if (it->second == "corridor") {
      opt->site = Site::kCorridor;
    } else {
      return absl::InvalidArgumentError("--site must be 'room' or 'corridor', got '" +
                                        it->second + "'");
    }
    kv.erase(it);
  }
  const int max_stations =
      static_cast<int>(opt->site == Site::kRoom ? SyntheticRoom::Default().Stations().size()
                                                : CorridorSite::Default().Stations().size());
  if (opt->site == Site::kCorridor) {
    opt->stations = max_stations;
    opt->project = "corridor-site";
  }
  if (auto s = get_int("--stations", 1, max_stations, &opt->stations); !s.ok()) return s;
  if (auto s = get_int("--pano-width", 8, 16384, &opt->pano_width_px); !s.ok()) return s;
  if (opt->pano_width_px % 2 != 0) return absl::InvalidArgumentError("--pano-width must be even");
  if (auto s = get_int("--lidar-azimuth-steps", 8, 20000, &opt->lidar_azimuth_steps); !s.ok()) {
    return s;
  }
  if (auto s = get_int("--lidar-elevation-steps", 4, 10000, &opt->lidar_elevation_steps);
      !s.ok()) {
    return s;
  }
  if (auto s = get_int("--supersample", 1, 16, &opt->supersample); !s.ok()) return s;
  if (it = kv.find("--seed"); it != kv.end()) {
    if (!absl::SimpleAtoi(it->second, &opt->seed)) {
      return absl::InvalidArgumentError("--seed must be a non-negative integer");
    }
    kv.erase(it);
  }
  if (it = kv.find("--project"); it != kv.end()) {
    if (it->second.empty()) return absl::InvalidArgumentError("--project must not be empty");
    opt->project = it->second;
    kv.erase(it);
  }
  if (it = kv.find("--vossel-size"); it != kv.end()) {
    if (!absl::SimpleAtod(it->second, &opt->vossel_size_m) || !(opt->vossel_size_m > 0.0)) {
      return absl::InvalidArgumentError("--vossel-size must be a positive number of metres");
    }
    kv.erase(it);
  }
  if (!kv.empty()) return absl::InvalidArgumentError("unknown option " + kv.begin()->first);
  return absl::OkStatus();
}

/// JSON string literal (names here are plain; quote and backslash escaped anyway).
std::string Quote(const std::string& s) {
  std::string out = "\"";
  for (char c : s) {
    if (c == '"' || c == '\\') out.push_back('\\');
    out.push_back(c);
  }
  return out + "\"";
}

std::string Vec(const Eigen::Vector3d& v) {
  return absl::StrFormat("[%.9g, %.9g, %.9g]", v.x() + 0.0, v.y() + 0.0, v.z() + 0.0);
}

std::string Quat(const Eigen::Quaterniond& q) {  // (x, y, z, w), the manifest's order
  // + 0.0 turns −0 into 0 so the JSON never shows "-0".
  return absl::StrFormat("[%.12g, %.12g, %.12g, %.12g]", q.x() + 0.0, q.y() + 0.0, q.z() + 0.0,
                         q.w() + 0.0);
}

std::string PoseJson(const geometry::Pose& p) {
  return absl::StrCat("{\"position\": ", Vec(p.o_world), ", \"quaternion\": ",
                      Quat(p.q_world_sensor), "}");
}

absl::Status WriteText(const fs::path& path, const std::string& text) {
  std::ofstream f(path, std::ios::binary | std::ios::trunc);
  if (!f) return absl::UnavailableError("cannot write " + path.string());
  f << text;
  f.close();
  if (!f) return absl::UnavailableError("write failed: " + path.string());
  return absl::OkStatus();
}

std::string PointList(const std::vector<Eigen::Vector3d>& pts) {
  std::vector<std::string> items;
  items.reserve(pts.size());
  for (const auto& p : pts) items.push_back(Vec(p));
  return "[" + absl::StrJoin(items, ", ") + "]";
}

/// Writes <view>-rgb.npy (H×W×3 linear) and <view>-depth.npy (H×W metres, +inf no hit).
absl::Status WriteTruth(const Panorama& pano, const fs::path& dir, const std::string& view) {
  const size_t h = pano.height_px, w = pano.width_px;
  if (auto st = WriteNpy(pano.rgb, {h, w, 3}, dir / (view + "-rgb.npy")); !st.ok()) return st;
  return WriteNpy(pano.depth_m, {h, w}, dir / (view + "-depth.npy"));
}

std::string BoxJson(const Aabb& box) {
  return absl::StrCat("{\"min\": ", Vec(box.min_m), ", \"max\": ", Vec(box.max_m), "}");
}

/// scene.json of the room site: `common` (project, vossel size, units), its geometry, then
/// `sensors` (camera offset, LiDAR, panorama, stations, novel views), then the shadow samples.
std::string RoomJson(const SyntheticRoom& room, const std::string& common,
                     const std::string& sensors) {
  return absl::StrCat(
      "{\n  \"scene\": \"synthetic-room\",\n", common,
      "\n  \"room\": ", BoxJson(room.RoomBounds()), ",\n  \"occluder\": ",
      BoxJson(room.OccluderBounds()), ",", sensors,
      "\n  \"shadow_samples_note\": \"points of wall y = max hidden by the occluder from scan-1 "
      "(LiDAR and camera) and visible from scan-2; lit_samples: visible from both\",",
      "\n  \"shadow_samples\": ", PointList(room.ShadowSamples()),
      ",\n  \"lit_samples\": ", PointList(room.LitSamples()), "\n}\n");
}

/// scene.json of the corridor site: `common`, the envelope, rooms, doors and solids, then
/// `sensors` and the station → room map.
std::string CorridorJson(const CorridorSite& site, const std::string& common,
                         const std::string& sensors) {
  std::vector<std::string> rooms, doors, solids, station_rooms;
  for (int i = 0; i < site.RoomCount(); ++i) rooms.push_back(BoxJson(site.RoomInterior(i)));
  for (const CorridorDoor& d : site.Doors()) {
    doors.push_back(absl::StrCat("    {\"opening\": ", BoxJson(d.opening), ", \"rooms\": [",
                                 d.room_xmin, ", ", d.room_xmax, "]}"));
  }
  for (const CorridorSolid& s : site.Solids()) {
    solids.push_back(absl::StrCat("    {\"kind\": ", Quote(CorridorSite::KindName(s.kind)),
                                  ", \"room\": ", s.room, ", \"box\": ", BoxJson(s.box), "}"));
  }
  for (size_t k = 0; k < site.Stations().size(); ++k) {
    station_rooms.push_back(absl::StrCat(site.StationRoom(k)));
  }
  return absl::StrCat(
      "{\n  \"scene\": \"corridor-site\",\n", common, "\n  \"bounds\": ",
      BoxJson(site.Bounds()), ",\n  \"rooms\": [", absl::StrJoin(rooms, ", "),
      "],\n  \"doors\": [\n", absl::StrJoin(doors, ",\n"), "\n  ],\n  \"solids\": [\n",
      absl::StrJoin(solids, ",\n"), "\n  ],", sensors,
      "\n  \"station_rooms\": [", absl::StrJoin(station_rooms, ", "), "]\n}\n");
}

absl::Status Run(const Options& opt) {
  const auto t0 = std::chrono::steady_clock::now();
  std::error_code ec;
  fs::create_directories(opt.out_dir / "truth", ec);
  if (ec) {
    return absl::UnavailableError("cannot create " + opt.out_dir.string() + ": " + ec.message());
  }

  const SyntheticRoom room = SyntheticRoom::Default();
  const CorridorSite corridor = CorridorSite::Default();
  const Scene& scene = opt.site == Site::kRoom ? static_cast<const Scene&>(room) : corridor;
  const std::vector<geometry::Pose> stations = scene.Stations();
  const int W = opt.pano_width_px, H = opt.pano_width_px / 2;
  LidarSettings lidar;
  lidar.azimuth_steps = opt.lidar_azimuth_steps;
  lidar.elevation_steps = opt.lidar_elevation_steps;

  struct View {
    std::string name;
    geometry::Pose pose;
  };
  std::vector<View> views;
  std::vector<std::string> station_json;
  size_t total_points = 0;

  for (int s = 0; s < opt.stations; ++s) {
    const std::string scan = absl::StrCat("scan-", s + 1);
    const geometry::Pose& T_world_scanner = stations[s];
    const geometry::Pose T_world_camera = CameraPoseForStation(T_world_scanner);

    lidar.seed = opt.seed * 1000003ull + static_cast<uint64_t>(s);
    const LidarScan points = GenerateLidar(scene, T_world_scanner, lidar);
    total_points += points.intensity.size();
    if (auto st = WritePly(points, opt.out_dir / (scan + ".ply")); !st.ok()) return st;

    const Panorama pano = RenderPanorama(scene, T_world_camera, W, H, opt.supersample);
    absl::StatusOr<std::string> png = EncodePng(pano);
    if (!png.ok()) return png.status();
    if (auto st = WriteText(opt.out_dir / (scan + "-rgb.png"), *png); !st.ok()) return st;
    const std::string view = scan + "-cam0";
    if (auto st = WriteTruth(pano, opt.out_dir / "truth", view); !st.ok()) return st;
    views.push_back({view, T_world_camera});

    const std::string manifest = absl::StrCat(
        "{\n  \"scan\": ", Quote(scan), ",\n  \"rig\": \"synthetic-rig\",\n",
        "  \"captured_utc\": ",
        Quote(absl::StrFormat("2026-11-22T%02d:%02d:00Z", 12 + (10 * s) / 60, (10 * s) % 60)),
        ",\n  \"pose\": ", PoseJson(T_world_scanner), ",\n",
        "  \"lidar\": {\"points\": ", Quote(scan + ".ply"), ", \"divergence_rad\": 0.0003},\n",
        "  \"panoramas\": [\n    {\"name\": \"cam0\", \"image\": ", Quote(scan + "-rgb.png"),
        ", \"modality\": \"rgb\",\n     \"pose\": ", PoseJson(T_world_camera), "}\n  ]\n}\n");
    if (auto st = WriteText(opt.out_dir / (scan + ".json"), manifest); !st.ok()) return st;
    station_json.push_back(absl::StrCat("    {\"scan\": ", Quote(scan), ", \"lidar_pose\": ",
                                        PoseJson(T_world_scanner), ",\n     \"camera_pose\": ",
                                        PoseJson(T_world_camera), ", \"points\": ",
                                        points.intensity.size(), "}"));
    std::printf("%s: %zu LiDAR points (%dx%d rays) -> %s.ply; %dx%d panorama -> %s-rgb.png; "
                "%s.json\n",
                scan.c_str(), points.intensity.size(), lidar.azimuth_steps, lidar.elevation_steps,
                scan.c_str(), W, H, scan.c_str(), scan.c_str());
  }

  const std::vector<geometry::Pose> novel = scene.NovelViews();
  for (size_t k = 0; k < novel.size(); ++k) {
    const std::string view = absl::StrCat("novel-", k + 1);
    const Panorama pano = RenderPanorama(scene, novel[k], W, H, opt.supersample);
    if (auto st = WriteTruth(pano, opt.out_dir / "truth", view); !st.ok()) return st;
    views.push_back({view, novel[k]});
  }

  // A camera-only scan: a pinhole photo from the first novel view (where no LiDAR stood),
  // looking along its +x and a little down, with a calibration's distortion.
  {
    const geometry::Pose photo_pose = LookAt(
        novel[0].o_world, novel[0].o_world + novel[0].DirectionToWorld({1.0, 0.0, -0.3}));
    const geometry::PinholeIntrinsics k = SurveyPhotoIntrinsics();
    const Panorama photo = RenderPinhole(scene, photo_pose, k, opt.supersample);
    absl::StatusOr<std::string> png = EncodePng(photo);
    if (!png.ok()) return png.status();
    if (auto st = WriteText(opt.out_dir / "photo-1.png", *png); !st.ok()) return st;
    if (auto st = WriteTruth(photo, opt.out_dir / "truth", "photo-1"); !st.ok()) return st;
    const std::string manifest = absl::StrCat(
        "{\n  \"scan\": \"photo-1\",\n  \"rig\": \"handheld\",\n  \"pose\": ",
        PoseJson(photo_pose), ",\n  \"panoramas\": [\n    {\"name\": \"photo\", \"image\": "
        "\"photo-1.png\", \"modality\": \"rgb\",\n     \"pose\": ", PoseJson(photo_pose),
        ",\n     \"pinhole\": ",
        absl::StrFormat("{\"fx_px\": %.9g, \"fy_px\": %.9g, \"cx_px\": %.9g, \"cy_px\": %.9g, "
                        "\"k1\": %.9g, \"k2\": %.9g, \"k3\": %.9g, \"p1\": %.9g, \"p2\": %.9g}",
                        k.fx_px, k.fy_px, k.cx_px, k.cy_px, k.k1, k.k2, k.k3, k.p1, k.p2),
        "}\n  ]\n}\n");
    if (auto st = WriteText(opt.out_dir / "photo-1.json", manifest); !st.ok()) return st;
    std::printf("photo-1: %dx%d pinhole photo from novel view 1, no LiDAR -> photo-1.png; "
                "photo-1.json\n", k.width_px, k.height_px);
  }

  std::vector<std::string> view_json;
  for (const View& v : views) {
    view_json.push_back(absl::StrCat("    {\"name\": ", Quote(v.name), ", \"position\": ",
                                     Vec(v.pose.o_world), ", \"quaternion\": ",
                                     Quat(v.pose.q_world_sensor), ", \"width\": ", W,
                                     ", \"height\": ", H, ",\n     \"rgb\": ",
                                     Quote(v.name + "-rgb.npy"), ", \"depth\": ",
                                     Quote(v.name + "-depth.npy"), "}"));
  }
  if (auto st = WriteText(opt.out_dir / "truth" / "views.json",
                          absl::StrCat("{\n  \"views\": [\n", absl::StrJoin(view_json, ",\n"),
                                       "\n  ]\n}\n"));
      !st.ok()) {
    return st;
  }

  std::vector<std::string> novel_json;
  for (size_t k = 0; k < novel.size(); ++k) {
    novel_json.push_back(absl::StrCat("    {\"name\": ", Quote(absl::StrCat("novel-", k + 1)),
                                      ", \"pose\": ", PoseJson(novel[k]), "}"));
  }
  const std::string common = absl::StrCat(
      "  \"project\": ", Quote(opt.project),
      ",\n  \"recommended_vossel_size_m\": ", absl::StrFormat("%.9g", opt.vossel_size_m),
      ",\n  \"units\": \"metres, world frame right-handed z up; quaternions (x, y, z, w)\",");
  const std::string sensors = absl::StrCat(
      "\n  \"camera_above_lidar_m\": ", absl::StrFormat("%.9g", kCameraAboveLidarM),
      ",\n  \"lidar\": {\"azimuth_steps\": ", lidar.azimuth_steps, ", \"elevation_steps\": ",
      lidar.elevation_steps, ", \"range_noise_m\": ", absl::StrFormat("%.9g", lidar.range_noise_m),
      ", \"nadir_blind_rad\": ", absl::StrFormat("%.9g", lidar.nadir_blind_rad),
      ", \"seed\": ", opt.seed, ", \"intensity\": \"Rec.709 luminance of the linear albedo\"},",
      "\n  \"panorama\": {\"width\": ", W, ", \"height\": ", H, ", \"supersample\": ",
      opt.supersample, ", \"encoding\": \"8-bit sRGB PNG of linear albedo (no lighting)\"},",
      "\n  \"stations\": [\n", absl::StrJoin(station_json, ",\n"), "\n  ],",
      "\n  \"novel_views\": [\n", absl::StrJoin(novel_json, ",\n"), "\n  ],");
  const std::string description = opt.site == Site::kRoom
                                      ? RoomJson(room, common, sensors)
                                      : CorridorJson(corridor, common, sensors);
  if (auto st = WriteText(opt.out_dir / "scene.json", description); !st.ok()) return st;

  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  std::printf("truth: %zu views (%dx%d rgb + depth .npy) -> %s/truth/, views.json\n", views.size(),
              W, H, opt.out_dir.string().c_str());
  std::printf("scene.json: project '%s', recommended vossel size %.3g m; %d scans, %zu points, "
              "%.1f s\n",
              opt.project.c_str(), opt.vossel_size_m, opt.stations, total_points, seconds);
  return absl::OkStatus();
}

}  // namespace
}  // namespace vasl::scenes

int main(int argc, char** argv) {
  vasl::scenes::Options opt;
  const absl::Status parsed = vasl::scenes::ParseArgs(argc, argv, &opt);
  if (absl::IsCancelled(parsed)) {
    std::fputs(vasl::scenes::kUsage, stdout);
    return 0;
  }
  if (!parsed.ok()) {
    std::fprintf(stderr, "vasl_scene: %s\n%s", std::string(parsed.message()).c_str(),
                 vasl::scenes::kUsage);
    return 2;
  }
  const absl::Status st = vasl::scenes::Run(opt);
  if (!st.ok()) {
    std::fprintf(stderr, "vasl_scene: %s\n", std::string(st.message()).c_str());
    return 1;
  }
  return 0;
}

// Claims of camera-only scans and pinhole cameras (VASL-MODEL §2.2, §3, §5): a scan of images
// without LiDAR points, taken where no LiDAR stood, colours the surfaces the project already
// has: its records lie on vossels the camera sees and carry their analytic colour, vossels the
// camera cannot see get none, and the geometry stays as it was. A pinhole photo records only
// the vossels its image holds, through its distortion.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>

#include <gtest/gtest.h>

#include "lattice/engine.h"
#include "lattice/geometry/pinhole.h"
#include "lattice/store/project_store.h"
#include "tests/scenes/synthetic_scene.h"

namespace vasl {
namespace {
namespace fs = std::filesystem;

constexpr double kVosselM = 0.05;
constexpr int kPanoW = 512;

class CameraOnlyTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new fs::path(fs::temp_directory_path() /
                        ("vasl-camera-only-test-" + std::to_string(::getpid())));
    fs::remove_all(*dir_);
    auto engine = Engine::Open(*dir_);
    ASSERT_TRUE(engine.ok()) << engine.status();
    engine_ = engine->release();
    store::ProjectSettings settings;
    settings.vossel_size_m = kVosselM;
    ASSERT_TRUE(engine_->CreateProject("room", settings).ok());
    room_ = new scenes::SyntheticRoom(scenes::SyntheticRoom::Default());
    for (size_t i = 0; i < room_->Stations().size(); ++i) {  // LiDAR only: no colour yet
      auto scan = scenes::MakeScanInput(*room_, i, scenes::LidarSettings::Small(i + 1), 0);
      ASSERT_TRUE(scan.ok()) << scan.status();
      auto r = engine_->IngestScan("room", *scan);
      ASSERT_TRUE(r.ok()) << r.status();
    }
    auto before = engine_->GetProject("room");
    ASSERT_TRUE(before.ok());
    vossels_before_ = before->vossel_count;

    // Two cameras where no LiDAR stood: a pinhole photo of the box with the wall behind it,
    // and a panorama at the other novel view.
    auto made = scenes::MakeCameraOnlyScan(
        *room_, "cameras", scenes::LookAt(room_->NovelViews()[0].o_world, {3.0, 3.3, 0.9}),
        room_->NovelViews()[1], kPanoW);
    ASSERT_TRUE(made.ok()) << made.status();
    ingest::ScanInput cameras = std::move(*made);
    auto r = engine_->IngestScan("room", cameras);
    ASSERT_TRUE(r.ok()) << r.status();
    result_ = new IngestResult(*r);
    std::printf("camera-only scan: v%lld, %lld vossels (before %lld), %lld sources computed, "
                "%lld revisited, %lld tiles written, %.2f s\n",
                (long long)r->version, (long long)r->vossel_count, (long long)vossels_before_,
                (long long)r->sources_computed, (long long)r->sources_revisited,
                (long long)r->tiles_changed, r->seconds);
    cameras_ = new ingest::ScanInput(std::move(cameras));

    // A fisheye photo (its field 2 × 110° across its width) where the photo stood: a
    // camera-only scan of its own, after the first.
    ingest::ScanInput fisheye;
    fisheye.scan_name = "fisheye";
    fisheye.rig = "handheld";
    fisheye.pose = scenes::LookAt(room_->NovelViews()[0].o_world, {3.0, 3.3, 0.9});
    ingest::PanoramaData photo;
    photo.name = "fisheye";
    photo.pose = fisheye.pose;
    photo.pinhole = FisheyeIntrinsics();
    auto png = scenes::EncodePng(scenes::RenderPinhole(*room_, photo.pose, *photo.pinhole, 2));
    ASSERT_TRUE(png.ok()) << png.status();
    photo.encoded_image = std::move(*png);
    fisheye.panoramas = {std::move(photo)};
    auto f = engine_->IngestScan("room", fisheye);
    ASSERT_TRUE(f.ok()) << f.status();
    fisheye_result_ = new IngestResult(*f);
  }
  // A 640 × 640 fisheye: Kannala–Brandt, 160 px per radian on its axis, a field of 2 × 110°
  // across its width (the corners 2 × 150°).
  static geometry::PinholeIntrinsics FisheyeIntrinsics() {
    geometry::PinholeIntrinsics k;
    k.width_px = k.height_px = 640;
    k.fx_px = k.fy_px = 160.0;
    k.cx_px = 320.5;
    k.cy_px = 318.0;
    k.lens = geometry::Lens::kFisheye;
    k.k1 = 0.021;
    k.k2 = -0.0048;
    k.k3 = 0.0011;
    k.k4 = 0.00005;
    return k;
  }
  static void TearDownTestSuite() {
    delete engine_;
    fs::remove_all(*dir_);
    delete dir_;
    delete room_;
    delete result_;
    delete cameras_;
    delete fisheye_result_;
  }

  // Figures of one camera source's records against the analytic scene.
  struct Check {
    size_t records = 0, hidden = 0, outside = 0;
    size_t seen = 0, seen_recorded = 0;  // vossels the camera sees squarely, and recorded
    std::vector<double> colour_error;    // lit records on the surface the camera sees (sorted)
    double ColourQuantile(double q) const {
      return colour_error[std::min(colour_error.size() - 1, size_t(double(colour_error.size()) * q))];
    }
    double SeenShare() const { return double(seen_recorded) / double(std::max<size_t>(1, seen)); }
    void Print(const char* what) const {
      std::printf("%s: %zu records, %zu outside the image, %zu on hidden vossels; %zu of %zu "
                  "squarely seen vossels recorded (%.2f%%); colour vs albedo over %zu lit "
                  "records: median %.4f, 99%% %.4f, max %.4f\n",
                  what, records, outside, hidden, seen_recorded, seen, 100.0 * SeenShare(),
                  colour_error.size(), ColourQuantile(0.5), ColourQuantile(0.99),
                  colour_error.back());
    }
  };

  // CheckSource on HEAD for camera `index` of the camera-only scan `scan`.
  static Check CheckCamera(size_t index, const geometry::PinholeIntrinsics* k,
                           const std::string& scan = "cameras") {
    auto st = store::ProjectStore::Open(*dir_ / "room");
    EXPECT_TRUE(st.ok()) << st.status();
    auto snap = (*st)->LoadSnapshot((*st)->head_version());
    EXPECT_TRUE(snap.ok()) << snap.status();
    const store::ScanInfo info = ScanNamed(scan);
    const store::SourceInfo& camera = info.sources.at(index);
    return CheckSource(**snap, camera.id, camera.pose, k);
  }
  // The records of the first camera of scan `scan` on vossels behind its image plane (more
  // than 90° from its axis).
  static size_t RecordsBehind(const std::string& scan) {
    const store::SourceInfo camera = ScanNamed(scan).sources.at(0);
    auto st = store::ProjectStore::Open(*dir_ / "room");
    EXPECT_TRUE(st.ok()) << st.status();
    auto snap = (*st)->LoadSnapshot((*st)->head_version());
    EXPECT_TRUE(snap.ok()) << snap.status();
    const records::RecordSet& rec = (*snap)->records;
    size_t behind = 0;
    for (size_t i = 0; i < rec.size(); ++i) {
      if (rec.scan[i] != camera.id) continue;
      const Eigen::Vector3d x =
          (*snap)->geometry.FrameCentroid(size_t(rec.vossel[i])).cast<double>();
      behind += camera.pose.WorldToSensor(x).z() < 0.0;
    }
    return behind;
  }
  static store::ScanInfo ScanNamed(const std::string& name) {
    auto scans = engine_->ListScans("room");
    EXPECT_TRUE(scans.ok()) << scans.status();
    for (const store::ScanInfo& s : *scans) {
      if (s.name == name) return s;
    }
    ADD_FAILURE() << "no scan " << name;
    return {};
  }

  // Every record of `source` and every vossel of the geometry, against the scene seen from
  // `pose` (`k` set: a pinhole camera, whose image must hold the vossel).
  static Check CheckSource(const store::Snapshot& snap, int32_t source, const geometry::Pose& pose,
                           const geometry::PinholeIntrinsics* k) {
    const records::VosselGeometry& g = snap.geometry;
    const records::RecordSet& rec = snap.records;
    const double h = kVosselM;
    const Eigen::Vector3d o = pose.o_world;
    // The analytic first hit along the ray to each vossel's centroid.
    auto first_hit = [&](const Eigen::Vector3d& x) {
      return room_->Intersect(o, (x - o).normalized(), 1e9);
    };
    auto in_image = [&](const Eigen::Vector3d& x, double margin_px) {
      if (k == nullptr) return true;
      const auto uv = geometry::PinholeProject(pose.WorldToSensor(x), *k);
      return uv && uv->x() >= margin_px && uv->x() <= k->width_px - margin_px &&
             uv->y() >= margin_px && uv->y() <= k->height_px - margin_px;
    };
    // Points of vossel v's surface patch (its frame's plane): the centroid and 8 points at
    // ±f·h along two tangents, and how many of them the camera sees on one face (-1: several).
    auto patch_seen = [&](size_t v, double f, int* face) {
      const Eigen::Vector3d x = g.FrameCentroid(v).cast<double>();
      const Eigen::Vector3d n = g.FrameNormal(v).cast<double>();
      const Eigen::Vector3d t1 = n.squaredNorm() > 0.5 ? n.unitOrthogonal() : Eigen::Vector3d::UnitX();
      const Eigen::Vector3d t2 = n.squaredNorm() > 0.5 ? n.cross(t1) : Eigen::Vector3d::UnitY();
      int seen = 0;
      *face = -2;
      for (int a = -1; a <= 1; ++a) {
        for (int b = -1; b <= 1; ++b) {
          const Eigen::Vector3d p = x + f * h * (a * t1 + b * t2);
          const scenes::SceneHit hit = first_hit(p);
          if (!hit.valid || hit.t_m < (p - o).norm() - 0.5 * h) continue;
          ++seen;
          *face = *face == -2 || *face == hit.face ? hit.face : -1;
        }
      }
      return seen;
    };
    auto cell_hidden = [&](size_t v) {
      const Eigen::Vector3d centre = h * Eigen::Vector3d(g.coord[v].x(), g.coord[v].y(), g.coord[v].z());
      for (int corner = 0; corner < 9; ++corner) {
        const Eigen::Vector3d p =
            corner == 8 ? centre
                        : centre + 0.5 * h * Eigen::Vector3d(corner & 1 ? 1 : -1, corner & 2 ? 1 : -1,
                                                             corner & 4 ? 1 : -1);
        const scenes::SceneHit hit = first_hit(p);
        if (!hit.valid || hit.t_m > (p - o).norm() - 2.0 * h) return false;
      }
      return true;
    };
    Check c;
    std::vector<uint8_t> recorded(g.size(), 0);
    for (size_t i = 0; i < rec.size(); ++i) {
      if (rec.scan[i] != source) continue;
      ++c.records;
      const size_t v = size_t(rec.vossel[i]);
      recorded[v] = 1;
      if (k != nullptr) {  // within half the uv codec's step (records.h: ≈ 0.25 px)
        constexpr float kHalfStep = 0.125f;
        c.outside += rec.uv_px[2 * i] < -kHalfStep ||
                     rec.uv_px[2 * i] > float(k->width_px) + kHalfStep ||
                     rec.uv_px[2 * i + 1] < -kHalfStep ||
                     rec.uv_px[2 * i + 1] > float(k->height_px) + kHalfStep;
      }
      // Hidden: a surface lies more than 2h in front of its whole cell (the centre and the 8
      // corners of the lattice cell, which holds every surface the vossel stands for).
      if (cell_hidden(v)) {
        ++c.hidden;
        continue;
      }
      int face;
      // Lit, and its whole patch (±h) on one face in sight: the record's colour is that face's.
      if (rec.vis[i] >= 1.0f && patch_seen(v, 1.0, &face) == 9 && face >= 0) {
        const Eigen::Vector3d x = g.FrameCentroid(v).cast<double>();
        const scenes::SceneHit hit = first_hit(x);
        double e = 0.0;
        for (int ch = 0; ch < 3; ++ch) {
          e = std::max(e, double(std::abs(rec.value[3 * i + ch] - hit.albedo_linear[ch])));
        }
        c.colour_error.push_back(e);
      }
    }
    // Seen squarely: at incidence under 60°, away from the image border, its whole patch (±h)
    // in sight on one face.
    for (size_t v = 0; v < g.size(); ++v) {
      const Eigen::Vector3d x = g.FrameCentroid(v).cast<double>();
      const Eigen::Vector3d n = g.FrameNormal(v).cast<double>();
      const double r = (x - o).norm();
      if (n.squaredNorm() < 0.5 || std::abs(n.dot(o - x)) / r < 0.5 || !in_image(x, 4.0)) continue;
      int face;
      if (patch_seen(v, 1.0, &face) != 9 || face < 0) continue;
      ++c.seen;
      c.seen_recorded += recorded[v];
    }
    std::sort(c.colour_error.begin(), c.colour_error.end());
    return c;
  }

  static inline fs::path* dir_ = nullptr;
  static inline Engine* engine_ = nullptr;
  static inline scenes::SyntheticRoom* room_ = nullptr;
  static inline IngestResult* result_ = nullptr;
  static inline IngestResult* fisheye_result_ = nullptr;
  static inline ingest::ScanInput* cameras_ = nullptr;
  static inline int64_t vossels_before_ = 0;
};

// Claim: a camera-only scan adds no geometry and revisits no older source (nothing it brings
// changes a depth panorama); it computes exactly its two cameras.
TEST_F(CameraOnlyTest, AddsNoGeometryAndRevisitsNothing) {
  EXPECT_EQ(result_->vossel_count, vossels_before_);
  EXPECT_EQ(result_->sources_computed, 2);
  EXPECT_EQ(result_->sources_revisited, 0);
  const store::ScanInfo last = ScanNamed("cameras");
  ASSERT_EQ(last.sources.size(), 2u);  // no LiDAR source
  EXPECT_EQ(last.sources[0].name, "photo");
  EXPECT_EQ(last.sources[0].width_px, 640);
  EXPECT_EQ(last.sources[0].camera.rfind("pinhole ", 0), 0u) << last.sources[0].camera;
  EXPECT_EQ(last.sources[1].name, "pano");
  EXPECT_TRUE(last.sources[1].camera.empty());
}

// Claim (§2.2, §3-§5): the pinhole photo's records lie inside its image, on vossels it sees;
// a vossel hidden from it gets no record; it records nearly every vossel it sees squarely;
// lit records carry the analytic albedo (the photo's pixels integrate the scene).
TEST_F(CameraOnlyTest, PinholePhotoColoursWhatItSeesAndNothingHidden) {
  const geometry::PinholeIntrinsics k = scenes::SurveyPhotoIntrinsics();
  const Check c = CheckCamera(0, &k);
  ASSERT_GT(c.colour_error.size(), 1000u);
  c.Print("pinhole photo");
  EXPECT_EQ(c.outside, 0u);
  EXPECT_EQ(c.hidden, 0u) << "a vossel hidden from the photo took its colour";
  EXPECT_GE(c.SeenShare(), 0.97);
  EXPECT_LT(c.ColourQuantile(0.5), 0.02);
  EXPECT_LT(c.ColourQuantile(0.99), 0.08);
}

// Claim (pinhole.h, fisheye lens): the same for a fisheye photo, through its Kannala–Brandt
// lens, on the walls it sees beyond 90° from its axis too; it adds no geometry and is stored
// as a fisheye.
TEST_F(CameraOnlyTest, FisheyePhotoColoursWhatItSeesAndNothingHidden) {
  EXPECT_EQ(fisheye_result_->vossel_count, vossels_before_);
  EXPECT_EQ(fisheye_result_->sources_revisited, 0);
  const store::ScanInfo scan = ScanNamed("fisheye");
  ASSERT_EQ(scan.sources.size(), 1u);
  EXPECT_EQ(scan.sources[0].camera.rfind("fisheye 160 160 320.5 318 ", 0), 0u)
      << scan.sources[0].camera;
  const geometry::PinholeIntrinsics k = FisheyeIntrinsics();
  const Check c = CheckCamera(0, &k, "fisheye");
  ASSERT_GT(c.colour_error.size(), 5000u);
  c.Print("fisheye photo");
  // Records beyond 90° from the axis: the lens sees behind its image plane.
  const size_t behind = RecordsBehind("fisheye");
  std::printf("fisheye photo: %zu records beyond 90 degrees from its axis\n", behind);
  EXPECT_GT(behind, 500u);
  EXPECT_EQ(c.outside, 0u);
  EXPECT_LE(double(c.hidden) / c.records, 0.002) << "vossels hidden from the fisheye took colour";
  EXPECT_GE(c.SeenShare(), 0.97);
  EXPECT_LT(c.ColourQuantile(0.5), 0.02);
  EXPECT_LT(c.ColourQuantile(0.99), 0.08);
}

// Claim (pinhole.h, a fisheye's field of view): a circular fisheye, black beyond its 180° image
// circle, sent with its field of view records nothing beyond 90° from its axis and only true
// colours; the same image without it would paint what lies beyond the circle black.
TEST_F(CameraOnlyTest, ACircularFisheyeSeesOnlyWithinItsFieldOfView) {
  geometry::PinholeIntrinsics k = FisheyeIntrinsics();
  k.field_of_view_rad = M_PI;
  const geometry::Pose pose = scenes::LookAt(room_->NovelViews()[1].o_world, {3.0, 3.3, 0.9});
  scenes::Panorama photo = scenes::RenderPinhole(*room_, pose, k, 2);
  size_t black = 0;
  for (int j = 0; j < k.height_px; ++j) {
    for (int i = 0; i < k.width_px; ++i) {
      if (geometry::PinholeSees(Eigen::Vector2d(i + 0.5, j + 0.5), k)) continue;
      std::fill_n(&photo.rgb[3 * (size_t(j) * size_t(k.width_px) + size_t(i))], 3, 0.0f);
      ++black;
    }
  }
  auto png = scenes::EncodePng(photo);
  ASSERT_TRUE(png.ok()) << png.status();
  auto ingest = [&](const std::string& name, const geometry::PinholeIntrinsics& lens) {
    ingest::ScanInput scan;
    scan.scan_name = name;
    scan.rig = "handheld";
    scan.pose = pose;
    ingest::PanoramaData data;
    data.name = name;
    data.pose = pose;
    data.pinhole = lens;
    data.encoded_image = *png;
    scan.panoramas = {std::move(data)};
    auto r = engine_->IngestScan("room", scan);
    ASSERT_TRUE(r.ok()) << r.status();
  };
  geometry::PinholeIntrinsics unbounded = k;
  unbounded.field_of_view_rad = 0.0;
  ingest("circular", k);
  ingest("circular-unbounded", unbounded);
  EXPECT_NE(ScanNamed("circular").sources.at(0).camera.find(" field 3.14159"), std::string::npos)
      << ScanNamed("circular").sources.at(0).camera;
  const Check c = CheckCamera(0, &k, "circular");
  const Check u = CheckCamera(0, &unbounded, "circular-unbounded");
  std::printf("circular fisheye, %zu of %d pixels black beyond its image circle:\n", black,
              k.width_px * k.height_px);
  c.Print("  with its 180-degree field");
  u.Print("  without it");
  const size_t behind = RecordsBehind("circular"), behind_unbounded =
                                                       RecordsBehind("circular-unbounded");
  std::printf("  records beyond 90 degrees: %zu with its field, %zu without\n", behind,
              behind_unbounded);
  EXPECT_GT(black, 50000u);
  EXPECT_EQ(behind, 0u);
  EXPECT_GT(behind_unbounded, 500u);
  EXPECT_LT(c.ColourQuantile(0.5), 0.02);
  EXPECT_LT(c.ColourQuantile(0.99), 0.08);
  EXPECT_GT(u.ColourQuantile(0.99), 0.2) << "the black surround should have painted vossels";
}

// Claim (§2.1, §5): the same for an equirect panorama that came without a LiDAR.
TEST_F(CameraOnlyTest, PanoramaWithoutLidarColoursWhatItSeesAndNothingHidden) {
  const Check c = CheckCamera(1, nullptr);
  ASSERT_GT(c.colour_error.size(), 5000u);
  c.Print("panorama");
  // A panorama of 512 columns has pixels of 0.7°; at the box's edges a hidden face lies within
  // the slope-scaled tolerance (§5: τ + r·Δ·tanθ over the dilated pixels) of the face in front
  // of it, and a few such vossels keep a penumbra or grazing record (measured 42, 0.10%).
  EXPECT_LE(double(c.hidden) / c.records, 0.005) << "vossels hidden from the panorama took colour";
  EXPECT_GE(c.SeenShare(), 0.97);
  EXPECT_LT(c.ColourQuantile(0.5), 0.02);
  EXPECT_LT(c.ColourQuantile(0.99), 0.08);
}

// Claim (ARCHITECTURE "Errors and limits"): a camera-only scan into a project without geometry
// and a pinhole photo with impossible intrinsics are refused with a message that says why, and
// leave the projects as they were.
TEST_F(CameraOnlyTest, RefusesWhatItCannotUse) {
  ASSERT_TRUE(engine_->CreateProject("empty", store::ProjectSettings{}).ok());
  ingest::ScanInput cameras = *cameras_;
  cameras.scan_name = "too-early";
  auto r = engine_->IngestScan("empty", cameras);
  ASSERT_EQ(r.status().code(), absl::StatusCode::kFailedPrecondition) << r.status();
  EXPECT_NE(r.status().message().find("no geometry"), std::string::npos) << r.status();
  auto empty = engine_->GetProject("empty");
  ASSERT_TRUE(empty.ok());
  EXPECT_EQ(empty->head_version, 0);

  auto before = engine_->GetProject("room");
  ASSERT_TRUE(before.ok());
  ingest::ScanInput bad = *cameras_;
  bad.scan_name = "bad-intrinsics";
  bad.panoramas[0].pinhole->fx_px = 0.0;
  r = engine_->IngestScan("room", bad);
  ASSERT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument) << r.status();
  EXPECT_NE(r.status().message().find("photo"), std::string::npos) << r.status();
  ingest::ScanInput nothing;
  nothing.scan_name = "nothing";
  nothing.pose = room_->NovelViews()[0];
  r = engine_->IngestScan("room", nothing);
  ASSERT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument) << r.status();
  auto after = engine_->GetProject("room");
  ASSERT_TRUE(after.ok());
  EXPECT_EQ(after->head_version, before->head_version);
}

}  // namespace
}  // namespace vasl

// VASL-MODEL §10, back-projection: a render sent back reproduces itself, λ_src = 0 excludes it,
// deleting its batch restores the fused tiles exactly, rebuild re-derives it bit for bit, and
// an edit changes exactly the vossels the edited pixels land on, by what the weights predict.
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <map>
#include <vector>

#include <gtest/gtest.h>

#include "lattice/engine.h"
#include "lattice/fusion/fuse.h"
#include "lattice/fusion/weight.h"
#include "lattice/geometry/equirect.h"
#include "lattice/geometry/footprint.h"
#include "lattice/geometry/pinhole.h"
#include "lattice/render/encode.h"
#include "lattice/store/project_store.h"
#include "tests/scenes/synthetic_scene.h"

namespace vasl {
namespace {
namespace fs = std::filesystem;

constexpr double kH = 0.05;

/// PSNR (peak 1) over the pixels both images cover.
double Psnr(const RenderImage& a, const RenderImage& b, int64_t* pixels) {
  double se = 0.0;
  int64_t n = 0;
  for (size_t p = 0; p < a.alpha.size(); ++p) {
    if (!(a.alpha[p] > 0.0f && b.alpha[p] > 0.0f)) continue;
    for (int c = 0; c < 3; ++c) se += std::pow(double(a.rgb[3 * p + c]) - b.rgb[3 * p + c], 2);
    ++n;
  }
  *pixels = n;
  return n == 0 ? 0.0 : 10.0 * std::log10(1.0 / (se / (3.0 * n) + 1e-30));
}

class BackProjectTest : public ::testing::Test {
 protected:
  void SetUp() override {
    root_ = fs::temp_directory_path() / ("vasl-backproject-" + std::to_string(::getpid()));
    fs::remove_all(root_);
    engine_ = std::move(*Engine::Open(root_));
    store::ProjectSettings settings;
    settings.vossel_size_m = kH;
    settings.tile_vossels = 32;
    ASSERT_TRUE(engine_->CreateProject("p", settings).ok());
    for (size_t i = 0; i < 2; ++i) {
      auto scan = scenes::MakeScanInput(room_, i, scenes::LidarSettings::Small(i + 1), 512, 2);
      ASSERT_TRUE(scan.ok());
      ASSERT_TRUE(engine_->IngestScan("p", *scan).ok());
    }
  }
  void TearDown() override { fs::remove_all(root_); }

  RenderImage Render(const std::string& profile = "") {
    RenderRequest req;
    req.pose = room_.NovelViews()[0];
    req.width_px = 512;
    req.height_px = 256;
    req.profile = profile;
    auto img = engine_->Render("p", req);
    EXPECT_TRUE(img.ok()) << img.status();
    return *img;
  }
  store::Manifest Manifest(int64_t v) {
    return *(*store::ProjectStore::Open(root_ / "p"))->LoadManifest(v);
  }
  static std::map<tiles::TileKey, std::string> Layer(const store::Manifest& m, const std::string& layer) {
    std::map<tiles::TileKey, std::string> out;
    for (const auto& [key, layers] : m.tiles) {
      auto it = layers.find(layer);
      if (it != layers.end()) out[key] = it->second.object;
    }
    return out;
  }

  fs::path root_;
  std::unique_ptr<Engine> engine_;
  const scenes::SyntheticRoom room_ = scenes::SyntheticRoom::Default();
};

// Claims (§10): a render back-projected and rendered again from the same pose reproduces itself
// (PSNR ≥ 40 dB); with λ_src = 0 the render equals the one before; deleting the batch gives back
// the previous fused tiles object for object; a rebuild re-derives the batch bit for bit.
TEST_F(BackProjectTest, RenderSentBackReproducesItselfAndRollsBack) {
  const RenderImage before = Render();
  auto exr = render::EncodeExr(before);
  ASSERT_TRUE(exr.ok());
  BackProjectInput in;
  in.name = "retouch-1";
  in.pose = room_.NovelViews()[0];
  in.image = *exr;
  in.render_id = before.render_id;
  auto r = engine_->BackProject("p", in);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->version, 3);
  const RenderImage after = Render();
  int64_t pixels = 0;
  const double psnr = Psnr(before, after, &pixels);
  fusion::WeightingProfile no_derived;
  no_derived.name = "raw-only";
  no_derived.lambda_src = 0.0;
  ASSERT_TRUE(engine_->CreateProfile("p", no_derived).ok());
  const RenderImage raw = Render("raw-only");
  std::printf("back-projection: %lld pixels -> derived records, %lld outside the lattice; render "
              "again: PSNR %.1f dB over %lld pixels; with lambda_src = 0 %s\n",
              (long long)r->pixels_back_projected, (long long)r->pixels_outside, psnr,
              (long long)pixels, raw.rgb == before.rgb ? "identical" : "DIFFERENT");
  EXPECT_GT(r->pixels_back_projected, 100000);
  EXPECT_GE(psnr, 40.0);
  EXPECT_EQ(raw.rgb, before.rgb);
  EXPECT_EQ(raw.uncertainty, before.uncertainty);

  // Rebuild re-derives the batch from its stored image: the same tiles.
  auto rebuilt = engine_->Rebuild("p");
  ASSERT_TRUE(rebuilt.ok()) << rebuilt.status();
  EXPECT_EQ(Layer(Manifest(3), store::kLayerRecords), Layer(Manifest(rebuilt->version), store::kLayerRecords));
  EXPECT_EQ(Layer(Manifest(3), store::kLayerFusedDefault),
            Layer(Manifest(rebuilt->version), store::kLayerFusedDefault));
  // Rolling the batch back: the fused tiles of version 2, object for object.
  auto gone = engine_->DeleteScan("p", "retouch-1");
  ASSERT_TRUE(gone.ok()) << gone.status();
  EXPECT_EQ(Layer(Manifest(2), store::kLayerFusedDefault),
            Layer(Manifest(gone->version), store::kLayerFusedDefault));
  EXPECT_EQ(Layer(Manifest(2), store::kLayerRecords), Layer(Manifest(gone->version), store::kLayerRecords));
  EXPECT_EQ(Render().rgb, before.rgb);
}

// Claim (§10): an edit (a region recoloured) changes exactly the vossels the region's pixels
// land on, each to (W·C + w_d·C_d) / (W + w_d) with W, C its fused weight and colour before and
// w_d the §7 weight of its derived record (λ_src = 0.5); every other vossel keeps its bits.
TEST_F(BackProjectTest, EditChangesExactlyTheVosselsItLandsOnByTheWeights) {
  RenderImage img = Render();
  const int W = img.width_px, H = img.height_px;
  const int i0 = W / 2 - 40, i1 = W / 2 + 40, j0 = H / 2 - 30, j1 = H / 2 + 30;
  RenderImage edited = img;
  for (size_t p = 0; p < edited.alpha.size(); ++p) {
    const int i = int(p % size_t(W)), j = int(p / size_t(W));
    const bool inside = i >= i0 && i < i1 && j >= j0 && j < j1;
    if (!inside) {
      edited.depth_m[p] = std::numeric_limits<float>::infinity();  // only the region comes back
      edited.alpha[p] = 0.0f;
      continue;
    }
    edited.rgb[3 * p + 0] = 0.9f;
    edited.rgb[3 * p + 1] = 0.1f;
    edited.rgb[3 * p + 2] = 0.1f;
  }
  auto st0 = *store::ProjectStore::Open(root_ / "p");
  auto before = *st0->LoadSnapshot(2);
  BackProjectInput in;
  in.pose = room_.NovelViews()[0];
  in.image = *render::EncodeExr(edited);
  auto r = engine_->BackProject("p", in);
  ASSERT_TRUE(r.ok()) << r.status();
  auto st = *store::ProjectStore::Open(root_ / "p");
  auto after = *st->LoadSnapshot(r->version);
  ASSERT_EQ(after->geometry.size(), before->geometry.size());

  // The vossels the region's pixels land on, found here independently.
  std::set<int32_t> landed;
  auto acc = after->geometry.index_grid->getConstAccessor();
  for (int j = j0; j < j1; ++j) {
    for (int i = i0; i < i1; ++i) {
      const size_t p = size_t(j) * W + i;
      if (!std::isfinite(edited.depth_m[p]) || !(edited.alpha[p] > 0.0f)) continue;
      const Eigen::Vector3d d = in.pose.DirectionToWorld(
          geometry::EquirectUnproject(i + 0.5, j + 0.5, {W, H})).normalized();
      const Eigen::Vector3d x = in.pose.o_world + double(edited.depth_m[p]) * d;
      int32_t v;
      if (acc.probeValue(openvdb::Coord(int(std::lround(x.x() / kH)), int(std::lround(x.y() / kH)),
                                        int(std::lround(x.z() / kH))), v)) {
        landed.insert(v);
      }
    }
  }
  const auto& fb = before->fused.by_modality.at(records::Modality::kRgb);
  const auto& fa = after->fused.by_modality.at(records::Modality::kRgb);
  const records::RecordSet& rec = after->records;
  std::map<int32_t, size_t> derived_of;
  for (size_t i = 0; i < rec.size(); ++i) {
    if (rec.modality[i] == int8_t(records::Modality::kDerived)) derived_of[rec.vossel[i]] = i;
  }
  int changed_outside = 0, checked = 0;
  double worst = 0.0;
  const fusion::WeightingProfile profile;
  for (size_t k = 0; k < after->geometry.size(); ++k) {
    const bool hit = landed.count(int32_t(k)) > 0;
    EXPECT_EQ(hit, derived_of.count(int32_t(k)) > 0) << "vossel " << k;
    if (!hit) {
      for (int c = 0; c < 3; ++c) changed_outside += fa.value[3 * k + c] != fb.value[3 * k + c];
      continue;
    }
    const size_t i = derived_of[int32_t(k)];
    const fusion::WeightInputs w = fusion::WeightInputsOf(rec, i);
    ASSERT_TRUE(w.derived);
    const double wd = fusion::RecordWeight(profile, w, geometry::TargetResolutionM(kH));
    const double wb = fb.weight[k];
    for (int c = 0; c < 3; ++c) {
      const double expect = (wb * fb.value[3 * k + c] + wd * rec.value[3 * i + c]) / (wb + wd);
      worst = std::max(worst, std::abs(expect - fa.value[3 * k + c]));
    }
    ++checked;
  }
  std::printf("edit of %dx%d pixels: %zu vossels landed on, %d checked against (W C + w_d C_d) / "
              "(W + w_d), worst %.2g; %d values changed elsewhere\n",
              i1 - i0, j1 - j0, landed.size(), checked, worst, changed_outside);
  EXPECT_GT(checked, 100);
  EXPECT_LT(worst, 1e-5);
  EXPECT_EQ(changed_outside, 0);
}

// Claim (§10, bad input): pixels whose colour is NaN or infinite (a compositor's divide by zero)
// are left out and counted, not averaged into NaN records: every derived record and every fused
// value stays finite, pixels_invalid counts exactly the poisoned surface pixels, and an image
// whose every surface pixel is poisoned is refused (INVALID_ARGUMENT) and commits nothing.
TEST_F(BackProjectTest, NonFiniteColoursAreLeftOutAndCounted) {
  RenderImage img = Render();
  const float kPoison[] = {std::numeric_limits<float>::quiet_NaN(),
                           std::numeric_limits<float>::infinity(),
                           -std::numeric_limits<float>::infinity()};
  int64_t poisoned = 0, surface = 0;
  RenderImage edited = img;
  for (size_t p = 0; p < edited.alpha.size(); ++p) {
    const bool lands = std::isfinite(edited.depth_m[p]) && edited.depth_m[p] > 0.0f &&
                       edited.alpha[p] > 0.0f;
    surface += lands;
    if (p % 7 != 0) continue;
    edited.rgb[3 * p + p % 3] = kPoison[(p / 7) % 3];  // one channel, one of three poisons
    poisoned += lands;
  }
  BackProjectInput in;
  in.pose = room_.NovelViews()[0];
  in.image = *render::EncodeExr(edited);
  auto r = engine_->BackProject("p", in);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->pixels_invalid, poisoned);
  EXPECT_EQ(r->pixels_back_projected + r->pixels_outside + r->pixels_invalid, surface);
  auto st = *store::ProjectStore::Open(root_ / "p");
  auto after = *st->LoadSnapshot(r->version);
  int64_t derived = 0, non_finite = 0;
  for (size_t i = 0; i < after->records.size(); ++i) {
    if (after->records.modality[i] != int8_t(records::Modality::kDerived)) continue;
    ++derived;
    for (int c = 0; c < 3; ++c) non_finite += !std::isfinite(after->records.value[3 * i + c]);
  }
  for (float v : after->fused.by_modality.at(records::Modality::kRgb).value) non_finite += !std::isfinite(v);
  std::printf("%lld of %lld surface pixels poisoned: pixels_invalid %lld, %lld back-projected, "
              "%lld derived records, %lld non-finite values\n",
              (long long)poisoned, (long long)surface, (long long)r->pixels_invalid,
              (long long)r->pixels_back_projected, (long long)derived, (long long)non_finite);
  EXPECT_GT(derived, 1000);
  EXPECT_EQ(non_finite, 0);

  RenderImage all_bad = img;
  for (float& v : all_bad.rgb) v = std::numeric_limits<float>::quiet_NaN();
  in.image = *render::EncodeExr(all_bad);
  auto refused = engine_->BackProject("p", in);
  ASSERT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument) << refused.status();
  EXPECT_NE(refused.status().message().find("NaN or infinite"), std::string::npos) << refused.status();
  auto versions = engine_->ListVersions("p");
  ASSERT_TRUE(versions.ok());
  EXPECT_EQ(versions->back().version, r->version);  // the refusal committed nothing
}

// Claim (§10 with §5): a scan ingested after a back-projection changes geometry where the batch's
// pixels land; the derived source is revisited on the changed blocks, and the result equals a
// rebuild (which re-derives the batch from its stored image) tile object for tile object.
TEST_F(BackProjectTest, LaterIngestKeepsDerivedRecordsEqualToARebuild) {
  const RenderImage view = Render();
  BackProjectInput in;
  in.pose = room_.NovelViews()[0];
  in.image = *render::EncodeExr(view);
  ASSERT_TRUE(engine_->BackProject("p", in).ok());  // v3
  auto scan = scenes::MakeScanInput(room_, 2, scenes::LidarSettings::Small(3), 512, 2);
  ASSERT_TRUE(scan.ok());
  auto r = engine_->IngestScan("p", *scan);  // v4
  ASSERT_TRUE(r.ok()) << r.status();
  auto rebuilt = engine_->Rebuild("p");  // v5
  ASSERT_TRUE(rebuilt.ok()) << rebuilt.status();
  const auto inc = Layer(Manifest(4), store::kLayerRecords), full = Layer(Manifest(5), store::kLayerRecords);
  int differ = 0;
  for (const auto& [key, object] : inc) differ += full.count(key) == 0 || full.at(key) != object;
  std::printf("ingest after a back-projection: %lld sources revisited (the derived one among "
              "them) on %lld blocks; %d of %zu record tiles differ from the rebuild\n",
              (long long)r->sources_revisited, (long long)r->blocks_revisited, differ, inc.size());
  EXPECT_EQ(differ, 0);
  EXPECT_EQ(inc.size(), full.size());
  EXPECT_EQ(Layer(Manifest(4), store::kLayerFusedDefault), Layer(Manifest(5), store::kLayerFusedDefault));
}

// Claim (§3 through §10): a fisheye image sent back gives each derived record the angle its
// pixels span where they look, the lens's own away from its axis: 2·atan(s_minor / r) of every
// record equals the larger of the two angles (radial, across) that a pixel at the record's mean
// pixel centre subtends, measured by unprojecting its edges, within 2%; records far off the
// axis have footprints grown as the lens's pitch grows there (k1 = −0.03: about 1.24× the
// axis's at 90°).
TEST_F(BackProjectTest, FisheyeRecordsTakeThePixelAngleWhereTheyLook) {
  geometry::PinholeIntrinsics k;
  k.width_px = k.height_px = 640;
  k.fx_px = k.fy_px = 200.0;
  k.cx_px = k.cy_px = 320.0;
  k.lens = geometry::Lens::kFisheye;
  k.k1 = -0.03;
  k.k2 = 0.001;
  const Eigen::Vector3d o = room_.NovelViews()[0].o_world;
  RenderRequest req;
  req.pose = scenes::LookAt(o, o + Eigen::Vector3d(1.0, 0.3, -0.2));
  req.width_px = k.width_px;
  req.height_px = k.height_px;
  req.projection = render::Projection::kPinhole;
  req.pinhole = k;
  auto view = engine_->Render("p", req);
  ASSERT_TRUE(view.ok()) << view.status();
  BackProjectInput in;
  in.name = "fisheye-retouch";
  in.pose = req.pose;
  in.pinhole = true;
  in.intrinsics = k;
  in.image = *render::EncodeExr(*view);
  auto r = engine_->BackProject("p", in);
  ASSERT_TRUE(r.ok()) << r.status();
  auto snapshot = (*store::ProjectStore::Open(root_ / "p"))->LoadSnapshot(r->version);
  ASSERT_TRUE(snapshot.ok()) << snapshot.status();
  const records::RecordSet& recs = (*snapshot)->records;

  // The pixel's angle measured at uv: its edges half a pixel either side, radially and across.
  const auto measured = [&k](const Eigen::Vector2d& uv) {
    Eigen::Vector2d radial = uv - Eigen::Vector2d(k.cx_px, k.cy_px);
    radial = radial.norm() > 1e-9 ? radial.normalized() : Eigen::Vector2d(1.0, 0.0);
    const Eigen::Vector2d across(-radial.y(), radial.x());
    double widest = 0.0;
    for (const Eigen::Vector2d& e : {radial, across}) {
      const Eigen::Vector3d a = geometry::PinholeUnproject(uv - 0.5 * e, k).normalized();
      const Eigen::Vector3d b = geometry::PinholeUnproject(uv + 0.5 * e, k).normalized();
      widest = std::max(widest, std::atan2(a.cross(b).norm(), a.dot(b)));
    }
    return widest;
  };
  const double axis = measured(Eigen::Vector2d(k.cx_px, k.cy_px));
  int64_t derived = 0, off_axis = 0;
  double worst = 0.0, widest_ratio = 0.0;
  for (size_t i = 0; i < recs.size(); ++i) {
    if (!(recs.flags[i] & records::kFlagDerived)) continue;
    const Eigen::Vector2d uv(recs.uv_px[2 * i], recs.uv_px[2 * i + 1]);
    const double want = measured(uv);
    const double got = 2.0 * std::atan(double(recs.foot_minor_m[i]) / double(recs.range_m[i]));
    worst = std::max(worst, std::abs(got / want - 1.0));
    const Eigen::Vector3d d = geometry::PinholeUnproject(uv, k).normalized();
    if (std::acos(std::clamp(d.z(), -1.0, 1.0)) > 80.0 * M_PI / 180.0) {
      ++off_axis;
      widest_ratio = std::max(widest_ratio, got / axis);
    }
    ++derived;
  }
  std::printf("fisheye back-projection: %lld derived records, %lld beyond 80 deg from the axis; "
              "pixel angle of the records against the one measured at their pixel: worst "
              "%.2f%%; widest %.3fx the axis's\n",
              (long long)derived, (long long)off_axis, 100.0 * worst, widest_ratio);
  EXPECT_GT(derived, 10000);
  EXPECT_GT(off_axis, 500);
  EXPECT_LE(worst, 0.02);
  EXPECT_GE(widest_ratio, 1.2);  // the axis's value everywhere would give 1
}

// Claims (§10, §8 multi-layer depth): a deep render sent back back-projects every layer: each
// sample is used, left outside the lattice or counted empty; the deeper layers land on surfaces
// the first layer never reaches (hidden from the pose), and their derived records carry those
// vossels' fused colours, which the deep render drew there (median error ≤ 0.01); a rebuild
// re-derives the deep batch from its stored image, record tile for record tile.
TEST_F(BackProjectTest, DeepRenderBackProjectsEveryLayer) {
  RenderRequest req;
  req.pose = room_.NovelViews()[0];
  req.width_px = 512;
  req.height_px = 256;
  req.layers = 3;
  auto deep = engine_->Render("p", req);
  ASSERT_TRUE(deep.ok()) << deep.status();
  auto deep_exr = render::EncodeDeepExr(*deep);
  ASSERT_TRUE(deep_exr.ok()) << deep_exr.status();
  int64_t samples = 0, coloured_samples = 0, deeper = 0;
  for (size_t p = 0; p < deep->layer_count.size(); ++p) {
    samples += deep->layer_count[p];
    for (size_t l = 0; l < deep->layer_count[p]; ++l) {
      const bool coloured = deep->deep_alpha[p * 3 + l] > 0.0f;
      coloured_samples += coloured;
      deeper += coloured && l > 0;
    }
  }
  BackProjectInput in;
  in.name = "deep-1";
  in.pose = req.pose;
  in.image = *deep_exr;
  in.render_id = deep->render_id;
  auto r = engine_->BackProject("p", in);  // v3
  ASSERT_TRUE(r.ok()) << r.status();
  auto store = store::ProjectStore::Open(root_ / "p");
  ASSERT_TRUE(store.ok());
  auto before = (*store)->LoadSnapshot(2);
  auto after = (*store)->LoadSnapshot(3);
  ASSERT_TRUE(before.ok() && after.ok());
  // The vossels the first layer lands on: where the flat render's pixels fall.
  std::vector<uint8_t> front((*after)->geometry.size(), 0);
  const double h = kH;
  auto acc = (*after)->geometry.index_grid->getConstAccessor();
  for (int j = 0; j < req.height_px; ++j) {
    for (int i = 0; i < req.width_px; ++i) {
      const size_t p = size_t(j) * req.width_px + i;
      if (!std::isfinite(deep->depth_m[p])) continue;
      const Eigen::Vector3d d = req.pose.DirectionToWorld(
          geometry::EquirectUnproject(i + 0.5, j + 0.5, {req.width_px, req.height_px}));
      const Eigen::Vector3d x = req.pose.o_world + double(deep->depth_m[p]) * d.normalized();
      int32_t v = -1;
      if (acc.probeValue(openvdb::Coord(int(std::lround(x.x() / h)), int(std::lround(x.y() / h)),
                                        int(std::lround(x.z() / h))), v)) {
        front[size_t(v)] = 1;
      }
    }
  }
  const records::RecordSet& recs = (*after)->records;
  const auto& fused = (*before)->fused.by_modality.at(records::Modality::kRgb);
  std::vector<double> hidden_err;
  int64_t derived = 0;
  for (size_t i = 0; i < recs.size(); ++i) {
    if (records::Modality(recs.modality[i]) != records::Modality::kDerived) continue;
    ++derived;
    const size_t k = size_t(recs.vossel[i]);
    if (front[k]) continue;
    double err = 0.0;
    for (int c = 0; c < 3; ++c) err = std::max(err, double(std::abs(recs.value[3 * i + c] - fused.value[3 * k + c])));
    hidden_err.push_back(err);
  }
  std::sort(hidden_err.begin(), hidden_err.end());
  const double median = hidden_err.empty() ? 1.0 : hidden_err[hidden_err.size() / 2];
  std::printf("deep back-projection: %lld samples (%lld coloured, %lld of them behind the first "
              "surface): %lld used, %lld outside, %lld empty; %lld derived records, %zu on vossels "
              "the first layer never reaches (median colour error %.4f)\n",
              (long long)samples, (long long)coloured_samples, (long long)deeper,
              (long long)r->pixels_back_projected, (long long)r->pixels_outside,
              (long long)(samples - r->pixels_back_projected - r->pixels_outside -
                          r->pixels_invalid),
              (long long)derived, hidden_err.size(), median);
  EXPECT_GT(deeper, 5000);
  EXPECT_GE(r->pixels_back_projected + r->pixels_outside, coloured_samples);
  EXPECT_LE(r->pixels_back_projected + r->pixels_outside + r->pixels_invalid, samples);
  EXPECT_GT(r->pixels_back_projected, coloured_samples - deeper + deeper / 2);
  EXPECT_GT(hidden_err.size(), 1000u);
  EXPECT_LE(median, 0.01);
  auto rebuilt = engine_->Rebuild("p");
  ASSERT_TRUE(rebuilt.ok()) << rebuilt.status();
  EXPECT_EQ(Layer(Manifest(3), store::kLayerRecords), Layer(Manifest(rebuilt->version), store::kLayerRecords));
}

}  // namespace
}  // namespace vasl

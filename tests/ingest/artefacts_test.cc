// VASL-MODEL §9, saturation and blooming: bright sources planted with a known bloom on sharp
// textures; the detected map finds the halos (precision, recall), leaves clean images at 1 and
// moves the colour a confidence-weighted blend gives toward the truth; the real panorama runs
// through it.
#include "lattice/ingest/artefacts.h"

#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include <OpenImageIO/imageio.h>
#include <gtest/gtest.h>
#include <tbb/task_arena.h>

#include "lattice/ingest/sources.h"
#include "tests/ingest/planted_panorama.h"

namespace vasl::ingest {
namespace {

// Claim (§9): around bright sources planted with a known bloom, the pixels whose bloom adds more
// than a tenth to their own light are found (precision and recall ≥ 0.9 over the pixels
// outside the clipped blobs), every clipped pixel has confidence 0, and a clipped surface that
// does not bloom gets no halo.
TEST(ArtefactsTest, SaturationMapFindsPlantedBlooming) {
  const int w = 1024, h = 512;
  const Planted planted = MakePanorama(w, h, PlantedSources(), /*sheet=*/true);
  const SaturationMap map = DetectSaturation(planted.image, /*wrap=*/true);
  ASSERT_EQ(map.conf.pixels.size(), size_t(w) * h);
  int64_t truth = 0, found = 0, both = 0, clipped = 0, clipped_zero = 0, sheet_halo = 0;
  for (size_t p = 0; p < map.conf.pixels.size(); ++p) {
    float m = 0.0f;
    for (int c = 0; c < 3; ++c) m = std::max(m, planted.image.pixels[3 * p + c]);
    if (m >= 0.999f) {
      ++clipped;
      clipped_zero += map.conf.pixels[p] == 0.0f;
      continue;
    }
    const bool is_halo = planted.bloom[p] > 0.1 * planted.surface[p] && planted.bloom[p] > 0.01;
    const bool said = map.conf.pixels[p] < 1.0f;
    truth += is_halo;
    found += said;
    both += is_halo && said;
    const int x = int(p % w), y = int(p / w);
    sheet_halo += said && x >= 480 && x < 580 && y >= 310 && y < 380;
  }
  const double precision = double(both) / double(std::max<int64_t>(1, found));
  const double recall = double(both) / double(std::max<int64_t>(1, truth));
  std::printf("blooming: %d blobs, %lld clipped pixels (all at 0: %d), halo %lld planted / %lld "
              "found / %lld both: precision %.3f, recall %.3f; largest halo %d px; %lld halo "
              "pixels around the clipped sheet; %.2f%% of the image below 1\n",
              map.blobs, (long long)clipped, int(clipped == clipped_zero), (long long)truth,
              (long long)found, (long long)both, precision, recall, map.max_halo_radius_px,
              (long long)sheet_halo, 100.0 * map.CoveredFraction(w, h));
  EXPECT_EQ(map.blobs, int(PlantedSources().size()) + 1);
  EXPECT_EQ(clipped_zero, clipped);
  EXPECT_EQ(map.clipped_pixels, clipped);
  EXPECT_GT(truth, 2000);
  EXPECT_GE(precision, 0.9);
  EXPECT_GE(recall, 0.9);
  EXPECT_EQ(sheet_halo, 0);
}

// Claim (§9): on clean images, textured as sharply, the map stays at 1 on ≥ 99% of the pixels,
// with or without a clipped surface that does not bloom.
TEST(ArtefactsTest, CleanImagesStayAtOne) {
  for (const bool sheet : {false, true}) {
    const Planted clean = MakePanorama(1024, 512, {}, sheet);
    const SaturationMap map = DetectSaturation(clean.image, true);
    int64_t below = 0;
    for (float c : map.conf.pixels) below += c < 1.0f;
    const double at_one = 1.0 - double(below) / (1024.0 * 512.0);
    std::printf("clean%s: %lld pixels below 1 (%lld clipped, %lld halo), %.3f%% at 1\n",
                sheet ? " with a clipped sheet" : "", (long long)below,
                (long long)map.clipped_pixels, (long long)map.halo_pixels, 100.0 * at_one);
    EXPECT_GE(at_one, 0.99);
    EXPECT_EQ(map.halo_pixels, 0);
  }
  geometry::LinearImage hdr = MakePanorama(64, 32, {}, false).image;
  hdr.clip_value = 0.0f;  // no clip level: nothing is saturated
  EXPECT_TRUE(DetectSaturation(hdr, true).conf.pixels.empty());
}

// Claim (issue "Reliability"): an image speckled with hundreds of thousands of clipped specks
// (a sensor's hot pixels, glitter) is mapped in bounded work: every speck is a blob at 0, and
// only the largest blobs' rings are measured.
TEST(ArtefactsTest, SpeckledImageIsMappedInBoundedWork) {
  geometry::LinearImage img = MakePanorama(2048, 1024, {}, false).image;
  int64_t specks = 0;
  for (int y = 1; y < img.height_px; y += 3) {
    for (int x = 1; x < img.width_px; x += 3) {
      for (int c = 0; c < 3; ++c) img.pixels[3 * (size_t(y) * img.width_px + x) + c] = 1.0f;
      ++specks;
    }
  }
  const SaturationMap map = DetectSaturation(img, true);
  int64_t zero = 0;
  for (float c : map.conf.pixels) zero += c == 0.0f;
  std::printf("speckled 2048x1024: %lld specks, %d blobs, %lld pixels at 0, %lld halo pixels\n",
              (long long)specks, map.blobs, (long long)zero, (long long)map.halo_pixels);
  EXPECT_EQ(map.blobs, specks);
  EXPECT_EQ(map.clipped_pixels, specks);
  EXPECT_EQ(zero, specks);
}

// Claim (§7 with §9): blending a bloomed view with a clean view of the same surface, weighted by
// conf^κ, moves the halo pixels' colour toward the surface's own: with κ = 1 the mean error is
// under 0.7 of that with κ = 0 (confidence ignored), and κ = 2 lowers it further.
TEST(ArtefactsTest, ConfidenceWeightingMovesHaloColourTowardTheTruth) {
  const Planted bloomed = MakePanorama(1024, 512, PlantedSources(), false);
  const Planted clean = MakePanorama(1024, 512, {}, false);
  const SaturationMap map = DetectSaturation(bloomed.image, true);
  double err[3] = {0.0, 0.0, 0.0};  // by κ
  int64_t pixels = 0;
  for (size_t p = 0; p < map.conf.pixels.size(); ++p) {
    if (!(BloomShare(bloomed, p) > 0.1)) continue;
    for (int kappa = 0; kappa < 3; ++kappa) {
      const double w = std::pow(double(map.conf.pixels[p]), kappa);
      for (int ch = 0; ch < 3; ++ch) {
        const double a = bloomed.image.pixels[3 * p + ch], truth = clean.image.pixels[3 * p + ch];
        err[kappa] += std::abs((w * a + truth) / (w + 1.0) - truth) / 3.0;
      }
    }
    ++pixels;
  }
  for (double& e : err) e /= double(pixels);
  std::printf("two-view blend over %lld bloomed pixels: mean |error| %.4f with confidence "
              "ignored (κ = 0), %.4f with κ = 1, %.4f with κ = 2\n", (long long)pixels, err[0],
              err[1], err[2]);
  EXPECT_GT(pixels, 2000);
  EXPECT_LT(err[1], 0.7 * err[0]);
  EXPECT_LT(err[2], err[1]);
}

// Claim (§9, real data): the real 8192×4096 panorama of ../shared/data runs through every
// detector: every pixel with a channel at the clip level, counted apart, is at 0 in its
// saturation map, and each map, written as a PNG for a person to look at, reads back at the
// image's size. The time is printed (speed goals live in the benchmark).
TEST(ArtefactsTest, RealPanoramaThroughEveryDetector) {
  const char* env = std::getenv("VASL_DATA_DIR");
  const std::filesystem::path jpg =
      std::filesystem::path(env != nullptr ? env : "../shared/data") / "panorama" /
      "image_atis_rcn_1.jpg";
  if (!std::filesystem::exists(jpg)) {
    GTEST_SKIP() << "real panorama not found at " << jpg << " (set VASL_DATA_DIR)";
  }
  std::ifstream in(jpg, std::ios::binary);
  const std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  auto image = DecodeImage(bytes, false, int64_t(8192) * 4096);
  ASSERT_TRUE(image.ok()) << image.status();
  const auto t0 = std::chrono::steady_clock::now();
  const ArtefactMaps maps = DetectArtefacts(*image, /*wrap=*/true);
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const SaturationMap& map = maps.saturation;
  const int w = image->width_px, h = image->height_px;
  int64_t clipped = 0, clipped_zero = 0;
  for (size_t p = 0; p < size_t(w) * size_t(h); ++p) {
    bool at_clip = false;
    for (int c = 0; c < image->channels; ++c) {
      at_clip |= image->pixels[p * image->channels + c] >= 0.999f * image->clip_value;
    }
    clipped += at_clip;
    clipped_zero += at_clip && !map.conf.pixels.empty() && map.conf.pixels[p] == 0.0f;
  }
  std::printf("real panorama %dx%d: every detector in %.2f s on %d threads\n", w, h, seconds,
              tbb::this_task_arena::max_concurrency());
  std::printf("  saturation: %d blobs, %lld clipped pixels, %lld halo pixels, %.3f%% of the "
              "image below 1, widest halo %d px\n",
              map.blobs, (long long)map.clipped_pixels, (long long)map.halo_pixels,
              100.0 * map.CoveredFraction(w, h), map.max_halo_radius_px);
  std::printf("  smear: %d columns, largest lift %.3f of the clip, %lld pixels lowered\n",
              maps.smear.columns, maps.smear.max_offset, (long long)maps.smear.soft_pixels);
  std::printf("  flare: %d sources with a veil, %lld invalid pixels, %lld soft, %.3f%% of the "
              "image below 1, farthest %d px\n",
              maps.flare.sources, (long long)maps.flare.invalid_pixels,
              (long long)maps.flare.soft_pixels, 100.0 * maps.flare.CoveredFraction(w, h),
              maps.flare.max_radius_px);
  std::printf("  codec: JPEG quality %.0f%s, %.3f%% of the image below 1\n", maps.codec.quality,
              maps.codec.chroma_subsampled ? ", chroma subsampled" : "",
              100.0 * maps.codec.CoveredFraction(w, h));
  geometry::LinearImage corrected = *image, moved;
  const int64_t moved_pixels = CorrectChannelShift(corrected, maps.fringing, &moved);
  std::printf("  fringing: %s; red (%+.2f, %+.2f) px, blue (%+.2f, %+.2f) px over %lld edge "
              "samples, largest tile offset %.2f px; %lld pixels moved by over a tenth\n",
              maps.fringing.found ? "corrected" : "none", maps.fringing.dx[0],
              maps.fringing.dy[0], maps.fringing.dx[2], maps.fringing.dy[2],
              (long long)maps.fringing.edges, maps.fringing.max_offset_px,
              (long long)moved_pixels);
  EXPECT_EQ(map.clipped_pixels, clipped);
  EXPECT_EQ(clipped_zero, clipped);
  EXPECT_TRUE(maps.codec.jpeg);
  const std::pair<const char*, const geometry::LinearImage*> written[] = {
      {"saturation", &map.conf}, {"smear", &maps.smear.conf}, {"flare", &maps.flare.conf},
      {"codec", &maps.codec.conf}, {"fringing", &moved}};
  for (const auto& [name, conf] : written) {
    auto png = EncodeConfidencePng(*conf, w, h);
    ASSERT_TRUE(png.ok()) << png.status();
    const std::filesystem::path out =
        std::filesystem::temp_directory_path() /
        ("vasl-real-panorama-" + std::string(name) + "-" + std::to_string(::getpid()) + ".png");
    std::ofstream(out, std::ios::binary) << *png;
    auto reader = OIIO::ImageInput::open(out.string());
    ASSERT_TRUE(reader != nullptr);
    const OIIO::ImageSpec spec = reader->spec();
    reader->close();
    std::printf("  %s map written to %s (%zu bytes)\n", name, out.c_str(), png->size());
    EXPECT_EQ(spec.width, w);
    EXPECT_EQ(spec.height, h);
    EXPECT_EQ(spec.nchannels, 1);
  }
}

}  // namespace
}  // namespace vasl::ingest

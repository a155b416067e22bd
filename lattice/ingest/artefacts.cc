/// @file artefacts.cc
/// @brief What the §9 detectors share: clipped blobs, the maps as images for a person, and
///        every detector run over one image (DetectArtefacts). Saturation and blooming live in
///        saturation.cc, flare in flare.cc, the codec in codec.cc, fringing in fringing.cc.
#include "lattice/ingest/artefacts.h"

#include <algorithm>
#include <cmath>
#include <memory>
#include <vector>

#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_reduce.h>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "lattice/ingest/artefacts_internal.h"

namespace vasl::ingest {
namespace internal {

ClippedBlobs FindClippedBlobs(const geometry::LinearImage& image, bool wrap) {
  ClippedBlobs out;
  const int W = image.width_px, H = image.height_px, C = image.channels;
  if (!(image.clip_value > 0.0f) || W <= 0 || H <= 0 || C <= 0 ||
      image.pixels.size() != size_t(W) * size_t(H) * size_t(C)) {
    return out;
  }
  const size_t n = size_t(W) * size_t(H);
  // Most images clip nowhere: find out before allocating anything.
  out.clipped_pixels = tbb::parallel_reduce(
      tbb::blocked_range<size_t>(0, n, 1 << 16), int64_t{0},
      [&](const tbb::blocked_range<size_t>& r, int64_t count) {
        for (size_t p = r.begin(); p != r.end(); ++p) {
          count += Level(image, p) >= kClipFraction;
        }
        return count;
      },
      [](int64_t a, int64_t b) { return a + b; });
  if (out.clipped_pixels == 0) return out;
  out.clipped.assign(n, 0);
  tbb::parallel_for(tbb::blocked_range<size_t>(0, n, 1 << 16),
                    [&](const tbb::blocked_range<size_t>& r) {
                      for (size_t p = r.begin(); p != r.end(); ++p) {
                        out.clipped[p] = Level(image, p) >= kClipFraction;
                      }
                    });

  // Blobs: 8-connected clipped regions (columns wrap on a panorama).
  std::vector<int32_t>& label = out.label;
  label.assign(n, -1);
  std::vector<int64_t>& area = out.area;
  std::vector<int>&box_x0 = out.box_x0, &box_x1 = out.box_x1;
  std::vector<int>&box_y0 = out.box_y0, &box_y1 = out.box_y1;
  const std::vector<uint8_t>& clipped = out.clipped;
  std::vector<size_t> stack;
  for (size_t s = 0; s < n; ++s) {
    if (!clipped[s] || label[s] >= 0) continue;
    const int32_t b = int32_t(area.size());
    area.push_back(0);
    box_x0.push_back(W), box_x1.push_back(-1), box_y0.push_back(H), box_y1.push_back(-1);
    const int seed_x = int(s % W);
    double sum_x = 0.0, sum_y = 0.0;
    label[s] = b;
    stack.push_back(s);
    while (!stack.empty()) {
      const size_t p = stack.back();
      stack.pop_back();
      const int x = int(p % W), y = int(p / W);
      ++area[b];
      // The centroid in columns unwrapped about the seed's (a blob across the seam).
      int ux = x;
      if (wrap && ux - seed_x > W / 2) ux -= W;
      if (wrap && seed_x - ux > W / 2) ux += W;
      sum_x += ux + 0.5;
      sum_y += y + 0.5;
      box_x0[b] = std::min(box_x0[b], x), box_x1[b] = std::max(box_x1[b], x);
      box_y0[b] = std::min(box_y0[b], y), box_y1[b] = std::max(box_y1[b], y);
      for (int dy = -1; dy <= 1; ++dy) {
        for (int dx = -1; dx <= 1; ++dx) {
          int xx = x + dx;
          const int yy = y + dy;
          if (yy < 0 || yy >= H) continue;
          if (xx < 0 || xx >= W) {
            if (!wrap) continue;
            xx = (xx + W) % W;
          }
          const size_t q = size_t(yy) * W + xx;
          if (clipped[q] && label[q] < 0) {
            label[q] = b;
            stack.push_back(q);
          }
        }
      }
    }
    out.centre_x.push_back(sum_x / double(area[b]));
    out.centre_y.push_back(sum_y / double(area[b]));
  }
  return out;
}

int BloomReachPx(int64_t area, int height_px) {
  const double r_b = std::sqrt(double(area) / M_PI);
  return std::min(std::max(8, height_px / 4), int(std::ceil(4.0 * r_b)) + 8);
}

}  // namespace internal

ArtefactMaps DetectArtefacts(const geometry::LinearImage& image, bool wrap) {
  const internal::ClippedBlobs blobs = internal::FindClippedBlobs(image, wrap);
  ArtefactMaps maps;
  maps.saturation = DetectSaturation(image, blobs);
  maps.smear = DetectSmear(image, blobs, wrap);
  maps.flare = DetectFlare(image, blobs, wrap);
  maps.codec = DetectCodec(image);
  maps.fringing = EstimateChannelShift(image, wrap);
  return maps;
}

absl::StatusOr<std::string> EncodeConfidencePng(const geometry::LinearImage& conf, int width_px,
                                                int height_px) {
  const size_t n = size_t(std::max(0, width_px)) * size_t(std::max(0, height_px));
  if (n == 0 || (!conf.pixels.empty() && conf.pixels.size() != n)) {
    return absl::InvalidArgumentError(absl::StrCat("a confidence map of ", conf.pixels.size(),
                                                   " values for a ", width_px, "x", height_px,
                                                   " image"));
  }
  std::vector<uint8_t> grey(n, 255);
  for (size_t p = 0; p < conf.pixels.size(); ++p) {
    grey[p] = uint8_t(std::lround(255.0f * std::clamp(conf.pixels[p], 0.0f, 1.0f)));
  }
  std::vector<unsigned char> bytes;
  OIIO::Filesystem::IOVecOutput proxy(bytes);
  std::unique_ptr<OIIO::ImageOutput> out = OIIO::ImageOutput::create("png");
  if (!out || !out->set_ioproxy(&proxy)) {
    return absl::InternalError("OpenImageIO cannot write a PNG to memory");
  }
  const OIIO::ImageSpec spec(width_px, height_px, 1, OIIO::TypeDesc::UINT8);
  if (!out->open("confidence.png", spec) || !out->write_image(OIIO::TypeDesc::UINT8, grey.data()) ||
      !out->close()) {
    return absl::InternalError(
        absl::StrCat("OpenImageIO failed to write the map: ", out->geterror()));
  }
  return std::string(bytes.begin(), bytes.end());
}

}  // namespace vasl::ingest

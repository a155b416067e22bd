#include "lattice/ingest/backproject.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <memory>

#include <OpenImageIO/imageio.h>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_sort.h>

#include "absl/strings/str_cat.h"
#include "lattice/geometry/equirect.h"
#include "lattice/geometry/footprint.h"
#include "lattice/geometry/pinhole.h"
#include "lattice/ingest/image_memory.h"
#include "lattice/records/record_grid.h"

namespace vasl::ingest {

absl::StatusOr<DerivedImage> DecodeRgbzImage(std::string_view bytes, int64_t max_pixels) {
  using namespace OIIO;
  absl::StatusOr<internal::MemoryImageInput> opened =
      internal::OpenImageInMemory(bytes, /*unassociated_alpha=*/true, max_pixels);
  if (!opened.ok()) {
    if (absl::IsResourceExhausted(opened.status())) return opened.status();
    return absl::InvalidArgumentError(absl::StrCat(
        "the RGBZ image does not decode (an OpenEXR file with channels R, G, B, Z is expected): ",
        opened.status().message()));
  }
  ImageInput* in = opened->in.get();
  const ImageSpec& spec = in->spec();
  if (spec.width <= 0 || spec.height <= 0) return absl::InvalidArgumentError("the RGBZ image is empty");
  if (int64_t(spec.width) * spec.height > max_pixels) {
    return absl::ResourceExhaustedError(absl::StrCat("RGBZ image of ", spec.width, "x", spec.height,
                                                     " pixels exceeds the limit of ", max_pixels));
  }
  if (spec.nchannels > 16) {
    return absl::ResourceExhaustedError(
        absl::StrCat("RGBZ image has ", spec.nchannels, " channels; at most 16 are read"));
  }
  std::map<std::string, int> index;
  for (int c = 0; c < spec.nchannels; ++c) index[spec.channel_name(c)] = c;
  for (const char* need : {"R", "G", "B", "Z"}) {
    if (!index.count(need)) {
      return absl::InvalidArgumentError(absl::StrCat(
          "the RGBZ image has no channel ", need, " (it needs R, G, B and Z; N.x, N.y, N.z, U "
          "and A are optional)"));
    }
  }
  const size_t n = size_t(spec.width) * spec.height;
  std::vector<float> all(n * size_t(spec.nchannels));
  if (!in->read_image(0, 0, 0, spec.nchannels, TypeDesc::FLOAT, all.data())) {
    return absl::InvalidArgumentError(absl::StrCat("the RGBZ image does not decode: ", in->geterror()));
  }
  in->close();
  DerivedImage out;
  out.width_px = spec.width;
  out.height_px = spec.height;
  auto plane = [&](std::initializer_list<const char*> names, std::vector<float>& dst) {
    for (const char* name : names) {
      if (!index.count(name)) return;
    }
    const size_t k = names.size();
    dst.resize(n * k);
    size_t c = 0;
    for (const char* name : names) {
      const int ch = index[name];
      for (size_t p = 0; p < n; ++p) dst[p * k + c] = all[p * size_t(spec.nchannels) + size_t(ch)];
      ++c;
    }
  };
  plane({"R", "G", "B"}, out.rgb);
  plane({"Z"}, out.depth_m);
  plane({"N.x", "N.y", "N.z"}, out.normal);
  plane({"U"}, out.uncertainty);
  plane({"A"}, out.alpha);
  return out;
}

records::RecordSet BackProjectRecords(const records::VosselGeometry& g, const DerivedSource& src,
                                      const std::vector<uint8_t>* only, BackProjectStats* stats) {
  const DerivedImage& im = src.image;
  const int W = im.width_px, H = im.height_px;
  const size_t n = size_t(W) * size_t(H);
  const double h = g.vossel_size_m;
  geometry::PinholeIntrinsics k = src.intrinsics;
  k.width_px = W;
  k.height_px = H;
  const geometry::EquirectSize size{W, H};
  // Pass 1, parallel: each pixel's vossel (−1: none).
  std::vector<int32_t> vossel_of(n, -1);
  std::vector<Eigen::Vector3d> dir(n);
  std::vector<int64_t> empty(size_t(H), 0), outside(size_t(H), 0), invalid(size_t(H), 0);
  tbb::parallel_for(tbb::blocked_range<int>(0, H), [&](const tbb::blocked_range<int>& rows) {
    auto acc = g.index_grid->getConstAccessor();
    for (int j = rows.begin(); j != rows.end(); ++j) {
      for (int i = 0; i < W; ++i) {
        const size_t p = size_t(j) * W + i;
        const double z = im.depth_m[p];
        if (!std::isfinite(z) || z <= 0.0 || (!im.alpha.empty() && !(im.alpha[p] > 0.0f))) {
          ++empty[size_t(j)];
          continue;
        }
        // A colour that is not a number cannot be averaged into a record (it would make the
        // record, and every fused value over it, NaN): the pixel is left out and counted.
        if (!std::isfinite(im.rgb[3 * p]) || !std::isfinite(im.rgb[3 * p + 1]) ||
            !std::isfinite(im.rgb[3 * p + 2])) {
          ++invalid[size_t(j)];
          continue;
        }
        const Eigen::Vector3d d_cam = src.pinhole
                                          ? geometry::PinholeUnproject(Eigen::Vector2d(i + 0.5, j + 0.5), k)
                                          : geometry::EquirectUnproject(i + 0.5, j + 0.5, size);
        const Eigen::Vector3d d = src.pose.DirectionToWorld(d_cam).normalized();
        const Eigen::Vector3d x = src.pose.o_world + z * d;
        const openvdb::Coord c(int(std::lround(x.x() / h)), int(std::lround(x.y() / h)),
                               int(std::lround(x.z() / h)));
        int32_t v = -1;
        if (!acc.probeValue(c, v) || v < 0 || (only != nullptr && !(*only)[size_t(v)])) {
          ++outside[size_t(j)];
          continue;
        }
        vossel_of[p] = v;
        dir[p] = d;
      }
    }
  });
  // Pass 2: pixels grouped by vossel, in pixel order within a vossel.
  std::vector<std::pair<int32_t, uint32_t>> order;
  order.reserve(n);
  for (size_t p = 0; p < n; ++p) {
    if (vossel_of[p] >= 0) order.emplace_back(vossel_of[p], uint32_t(p));
  }
  tbb::parallel_sort(order.begin(), order.end());
  std::vector<size_t> starts;
  for (size_t i = 0; i < order.size(); ++i) {
    if (i == 0 || order[i].first != order[i - 1].first) starts.push_back(i);
  }
  starts.push_back(order.size());
  const size_t m = starts.size() - 1;
  records::RecordSet out;
  out.Resize(m);
  const double theta_pix = src.pinhole ? geometry::PinholePixelAngleRad(k)
                                       : geometry::EquirectPixelAngleRad(0.0, size);
  tbb::parallel_for(tbb::blocked_range<size_t>(0, m, 256), [&](const tbb::blocked_range<size_t>& r) {
    for (size_t q = r.begin(); q != r.end(); ++q) {
      const int32_t v = order[starts[q]].first;
      double rgb[3] = {0, 0, 0}, range = 0, cos_sum = 0, u = 0, vv = 0, unc = 0;
      const double count = double(starts[q + 1] - starts[q]);
      const Eigen::Vector3d n_k = g.FrameNormal(size_t(v)).cast<double>();
      for (size_t e = starts[q]; e < starts[q + 1]; ++e) {
        const size_t p = order[e].second;
        for (int c = 0; c < 3; ++c) rgb[c] += im.rgb[3 * p + c];
        range += im.depth_m[p];
        const Eigen::Vector3d& d = dir[p];
        if (!im.normal.empty()) {
          const Eigen::Vector3d np(im.normal[3 * p], im.normal[3 * p + 1], im.normal[3 * p + 2]);
          cos_sum += np.squaredNorm() > 0.25 ? std::abs(np.normalized().dot(d)) : 1.0;
        } else {
          cos_sum += n_k.squaredNorm() > 0.25 ? std::abs(n_k.dot(d)) : 1.0;
        }
        u += double(p % size_t(W)) + 0.5;
        vv += double(p / size_t(W)) + 0.5;
        if (!im.uncertainty.empty() && std::isfinite(im.uncertainty[p])) unc += im.uncertainty[p];
      }
      const double cos_inc = std::clamp(cos_sum / count, 0.0, 1.0);
      const double range_m = range / count;
      const geometry::SurfaceFootprint foot = geometry::SurfaceFootprintAt(range_m, theta_pix, cos_inc);
      out.vossel[q] = v;
      out.scan[q] = src.id;
      out.modality[q] = int8_t(records::Modality::kDerived);
      for (int c = 0; c < 3; ++c) out.value[q * 3 + c] = float(rgb[c] / count);
      out.range_m[q] = float(range_m);
      out.cos_inc[q] = float(cos_inc);
      out.foot_major_m[q] = float(foot.major_m);
      out.foot_minor_m[q] = float(foot.minor_m);
      out.uv_px[2 * q] = float(u / count);
      out.uv_px[2 * q + 1] = float(vv / count);
      out.vis[q] = 1.0f;  // §10
      for (int f = 0; f < records::kConfidenceCount; ++f) out.conf[q * records::kConfidenceCount + f] = 1.0f;
      out.conf[q * records::kConfidenceCount + records::kConfCodec] = float(1.0 / (1.0 + (unc / count) / 0.1));
      out.flags[q] = records::kFlagDerived;
      out.batch[q] = src.batch;
    }
  });
  records::RoundToStorage(out);
  if (stats != nullptr) {
    stats->pixels_used = int64_t(order.size());
    for (int j = 0; j < H; ++j) {
      stats->pixels_empty += empty[size_t(j)];
      stats->pixels_outside += outside[size_t(j)];
      stats->pixels_invalid += invalid[size_t(j)];
    }
  }
  return out;
}

}  // namespace vasl::ingest

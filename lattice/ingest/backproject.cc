#include "lattice/ingest/backproject.h"

#include <algorithm>
#include <cstring>
#include <cmath>
#include <map>
#include <memory>

#include <OpenEXR/Iex.h>
#include <OpenEXR/ImfChannelList.h>
#include <OpenEXR/ImfDeepFrameBuffer.h>
#include <OpenEXR/ImfDeepScanLineInputFile.h>
#include <OpenEXR/ImfHeader.h>
#include <OpenEXR/ImfIO.h>
#include <OpenImageIO/imageio.h>
#include <tbb/blocked_range.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_sort.h>

#include "absl/strings/str_cat.h"
#include "lattice/geometry/equirect.h"
#include "lattice/geometry/footprint.h"
#include "lattice/geometry/image_projection.h"
#include "lattice/geometry/pinhole.h"
#include "lattice/ingest/image_memory.h"
#include "lattice/records/record_grid.h"

namespace vasl::ingest {

namespace {

/// An OpenEXR input stream over bytes in memory.
class MemoryIStream : public Imf::IStream {
 public:
  explicit MemoryIStream(std::string_view bytes) : Imf::IStream("deep RGBZ image"), bytes_(bytes) {}
  bool read(char c[], int n) override {
    if (n < 0 || pos_ > bytes_.size() || uint64_t(n) > bytes_.size() - pos_) {
      throw Iex::InputExc("the deep image ends early");
    }
    std::memcpy(c, bytes_.data() + pos_, size_t(n));
    pos_ += uint64_t(n);
    return pos_ < bytes_.size();
  }
  uint64_t tellg() override { return pos_; }
  void seekg(uint64_t pos) override { pos_ = pos; }

 private:
  std::string_view bytes_;
  uint64_t pos_ = 0;
};

/// Rows of a deep image read at a time (bounds the per-pixel sample pointers held at once).
constexpr int kDeepBandRows = 64;

/// A deep scan-line OpenEXR's samples (R, G, B, Z required; A when present), pixel by pixel.
absl::StatusOr<DerivedImage> DecodeDeepRgbz(std::string_view bytes, int64_t max_samples) {
  DerivedImage out;
  try {
    MemoryIStream stream(bytes);
    Imf::DeepScanLineInputFile file(stream);
    const Imath::Box2i dw = file.header().dataWindow();
    const int64_t W = int64_t(dw.max.x) - dw.min.x + 1, H = int64_t(dw.max.y) - dw.min.y + 1;
    if (W <= 0 || H <= 0) return absl::InvalidArgumentError("the deep RGBZ image is empty");
    if (W * H > max_samples) {
      return absl::ResourceExhaustedError(absl::StrCat("deep RGBZ image of ", W, "x", H,
                                                       " pixels exceeds the limit of ", max_samples));
    }
    const Imf::ChannelList& channels = file.header().channels();
    for (const char* need : {"R", "G", "B", "Z"}) {
      if (channels.findChannel(need) == nullptr) {
        return absl::InvalidArgumentError(absl::StrCat(
            "the deep RGBZ image has no channel ", need, " (it needs R, G, B and Z; A is optional)"));
      }
    }
    const bool has_alpha = channels.findChannel("A") != nullptr;
    const size_t n = size_t(W) * size_t(H);
    std::vector<unsigned int> count(n, 0);
    // Slices address pixel (x, y) of the data window at base + x·xStride + y·yStride.
    const ptrdiff_t origin = ptrdiff_t(dw.min.x) + ptrdiff_t(dw.min.y) * ptrdiff_t(W);
    Imf::DeepFrameBuffer counts;
    counts.insertSampleCountSlice(Imf::Slice(Imf::UINT, reinterpret_cast<char*>(count.data() - origin),
                                             sizeof(unsigned int), sizeof(unsigned int) * W));
    file.setFrameBuffer(counts);
    file.readPixelSampleCounts(dw.min.y, dw.max.y);
    std::vector<size_t> first(n + 1, 0);
    for (size_t p = 0; p < n; ++p) {
      first[p + 1] = first[p] + count[p];
      if (int64_t(first[p + 1]) > max_samples) {
        return absl::ResourceExhaustedError(absl::StrCat(
            "the deep RGBZ image holds more than ", max_samples, " samples (the limit)"));
      }
    }
    const size_t total = first[n];
    std::vector<float> r(total), g(total), b(total), z(total), a(has_alpha ? total : 0);
    std::vector<std::pair<const char*, std::vector<float>*>> planes = {
        {"R", &r}, {"G", &g}, {"B", &b}, {"Z", &z}};
    if (has_alpha) planes.emplace_back("A", &a);
    std::vector<std::vector<char*>> pointers(planes.size(), std::vector<char*>(size_t(W) * kDeepBandRows));
    for (int64_t y0 = 0; y0 < H; y0 += kDeepBandRows) {
      const int64_t y1 = std::min<int64_t>(H, y0 + kDeepBandRows);
      Imf::DeepFrameBuffer frame;
      frame.insertSampleCountSlice(Imf::Slice(Imf::UINT, reinterpret_cast<char*>(count.data() - origin),
                                              sizeof(unsigned int), sizeof(unsigned int) * W));
      const ptrdiff_t band_origin = ptrdiff_t(dw.min.x) + ptrdiff_t(dw.min.y + y0) * ptrdiff_t(W);
      for (size_t c = 0; c < planes.size(); ++c) {
        std::vector<char*>& ptr = pointers[c];
        for (int64_t p = y0 * W; p < y1 * W; ++p) {
          ptr[size_t(p - y0 * W)] = reinterpret_cast<char*>(planes[c].second->data() + first[size_t(p)]);
        }
        frame.insert(planes[c].first,
                     Imf::DeepSlice(Imf::FLOAT, reinterpret_cast<char*>(ptr.data() - band_origin),
                                    sizeof(char*), sizeof(char*) * W, sizeof(float)));
      }
      file.setFrameBuffer(frame);  // a new frame buffer reads its rows' counts again
      file.readPixelSampleCounts(int(dw.min.y + y0), int(dw.min.y + y1 - 1));
      file.readPixels(int(dw.min.y + y0), int(dw.min.y + y1 - 1));
    }
    out.width_px = int(W);
    out.height_px = int(H);
    out.rgb.resize(3 * total);
    out.depth_m = std::move(z);
    out.alpha = std::move(a);
    out.sample_pixel.resize(total);
    for (size_t p = 0; p < n; ++p) {
      for (size_t s = first[p]; s < first[p + 1]; ++s) out.sample_pixel[s] = uint32_t(p);
    }
    for (size_t s = 0; s < total; ++s) {
      out.rgb[3 * s] = r[s];
      out.rgb[3 * s + 1] = g[s];
      out.rgb[3 * s + 2] = b[s];
    }
  } catch (const std::exception& e) {
    return absl::InvalidArgumentError(absl::StrCat("the deep RGBZ image does not decode: ", e.what()));
  }
  return out;
}

}  // namespace

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
  if (spec.deep) {  // a deep render (§8): every sample of every pixel
    in->close();
    return DecodeDeepRgbz(bytes, max_pixels);
  }
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
  const size_t n = im.SampleCount();  // pixels, or a deep image's samples
  const bool deep = !im.sample_pixel.empty();
  auto pixel_of = [&](size_t s) { return deep ? size_t(im.sample_pixel[s]) : s; };
  const double h = g.vossel_size_m;
  geometry::PinholeIntrinsics k = src.intrinsics;
  k.width_px = W;
  k.height_px = H;
  const geometry::EquirectSize size{W, H};
  // Pass 1, parallel: each pixel's (sample's) vossel (−1: none).
  std::vector<int32_t> vossel_of(n, -1);
  std::vector<Eigen::Vector3d> dir(n);
  struct Counts {
    int64_t empty = 0, outside = 0, invalid = 0;
  };
  tbb::enumerable_thread_specific<Counts> counts;
  tbb::parallel_for(tbb::blocked_range<size_t>(0, n, 4096), [&](const tbb::blocked_range<size_t>& r) {
    auto acc = g.index_grid->getConstAccessor();
    Counts& local = counts.local();
    for (size_t p = r.begin(); p != r.end(); ++p) {
      const double z = im.depth_m[p];
      if (!std::isfinite(z) || z <= 0.0 || (!im.alpha.empty() && !(im.alpha[p] > 0.0f))) {
        ++local.empty;
        continue;
      }
      // A colour that is not a number cannot be averaged into a record (it would make the
      // record, and every fused value over it, NaN): the pixel is left out and counted.
      if (!std::isfinite(im.rgb[3 * p]) || !std::isfinite(im.rgb[3 * p + 1]) ||
          !std::isfinite(im.rgb[3 * p + 2])) {
        ++local.invalid;
        continue;
      }
      const size_t pixel = pixel_of(p);
      const Eigen::Vector2d centre(double(pixel % size_t(W)) + 0.5, double(pixel / size_t(W)) + 0.5);
      const Eigen::Vector3d d_cam = src.pinhole ? geometry::PinholeUnproject(centre, k)
                                                : geometry::EquirectUnproject(centre.x(), centre.y(), size);
      const Eigen::Vector3d d = src.pose.DirectionToWorld(d_cam).normalized();
      const Eigen::Vector3d x = src.pose.o_world + z * d;
      const openvdb::Coord c(int(std::lround(x.x() / h)), int(std::lround(x.y() / h)),
                             int(std::lround(x.z() / h)));
      int32_t v = -1;
      if (!acc.probeValue(c, v) || v < 0 || (only != nullptr && !(*only)[size_t(v)])) {
        ++local.outside;
        continue;
      }
      vossel_of[p] = v;
      dir[p] = d;
    }
  });
  // Pass 2: pixels (samples) grouped by vossel, in pixel order within a vossel.
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
  // §3's θ_pix where the vossel's pixels look (a fisheye's and a panorama's vary with it).
  const geometry::ImageProjection projection(
      src.pinhole ? std::optional<geometry::PinholeIntrinsics>(k) : std::nullopt, W, H);
  tbb::parallel_for(tbb::blocked_range<size_t>(0, m, 256), [&](const tbb::blocked_range<size_t>& r) {
    for (size_t q = r.begin(); q != r.end(); ++q) {
      const int32_t v = order[starts[q]].first;
      double rgb[3] = {0, 0, 0}, range = 0, cos_sum = 0, u = 0, vv = 0, unc = 0;
      Eigen::Vector3d dir_sum = Eigen::Vector3d::Zero();
      const double count = double(starts[q + 1] - starts[q]);
      const Eigen::Vector3d n_k = g.FrameNormal(size_t(v)).cast<double>();
      for (size_t e = starts[q]; e < starts[q + 1]; ++e) {
        const size_t p = order[e].second;
        for (int c = 0; c < 3; ++c) rgb[c] += im.rgb[3 * p + c];
        range += im.depth_m[p];
        const Eigen::Vector3d& d = dir[p];
        dir_sum += d;
        if (!im.normal.empty()) {
          const Eigen::Vector3d np(im.normal[3 * p], im.normal[3 * p + 1], im.normal[3 * p + 2]);
          cos_sum += np.squaredNorm() > 0.25 ? std::abs(np.normalized().dot(d)) : 1.0;
        } else {
          cos_sum += n_k.squaredNorm() > 0.25 ? std::abs(n_k.dot(d)) : 1.0;
        }
        u += double(pixel_of(p) % size_t(W)) + 0.5;
        vv += double(pixel_of(p) / size_t(W)) + 0.5;
        if (!im.uncertainty.empty() && std::isfinite(im.uncertainty[p])) unc += im.uncertainty[p];
      }
      const double cos_inc = std::clamp(cos_sum / count, 0.0, 1.0);
      const double range_m = range / count;
      const double theta_pix = projection.PixelAngleRad(src.pose.DirectionToSensor(dir_sum));
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
    for (const Counts& c : counts) {
      stats->pixels_empty += c.empty;
      stats->pixels_outside += c.outside;
      stats->pixels_invalid += c.invalid;
    }
  }
  return out;
}

}  // namespace vasl::ingest

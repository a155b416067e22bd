/// @file encode.cc
/// @brief EXR (OpenEXR C++ API, in memory) and PNG (OpenImageIO, in memory) encoders of a
///        RenderImage (VASL-MODEL §8 outputs).
#include "lattice/render/encode.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <exception>
#include <memory>
#include <vector>

#include <OpenEXR/ImfChannelList.h>
#include <OpenEXR/ImfPartType.h>
#include <OpenEXR/ImfCompression.h>
#include <OpenEXR/ImfFrameBuffer.h>
#include <OpenEXR/ImfHeader.h>
#include <OpenEXR/ImfIO.h>
#include <OpenEXR/ImfLineOrder.h>
#include <OpenEXR/ImfDeepFrameBuffer.h>
#include <OpenEXR/ImfDeepScanLineOutputFile.h>
#include <OpenEXR/ImfOutputFile.h>
#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"

namespace vasl::render {
namespace {

/// An Imf::OStream appending to (and seeking within) a std::string.
class StringOStream : public Imf::OStream {
 public:
  explicit StringOStream(std::string* bytes) : Imf::OStream("memory.exr"), bytes_(bytes) {}

  void write(const char c[], int n) override {
    const size_t end = pos_ + static_cast<size_t>(n);
    if (end > bytes_->size()) bytes_->resize(end);
    std::memcpy(bytes_->data() + pos_, c, static_cast<size_t>(n));
    pos_ = end;
  }
  uint64_t tellp() override { return pos_; }
  void seekp(uint64_t pos) override { pos_ = static_cast<size_t>(pos); }

 private:
  std::string* bytes_;  ///< not owned
  size_t pos_ = 0;      ///< write position, bytes
};

absl::Status ValidateImage(const RenderImage& image) {
  if (image.width_px <= 0 || image.height_px <= 0) {
    return absl::InvalidArgumentError(absl::StrCat("image size must be positive, got ",
                                                   image.width_px, "x", image.height_px));
  }
  const size_t pixels = static_cast<size_t>(image.width_px) * image.height_px;
  if (image.rgb.size() != 3 * pixels || image.depth_m.size() != pixels ||
      image.normal.size() != 3 * pixels || image.uncertainty.size() != pixels ||
      (!image.alpha.empty() && image.alpha.size() != pixels)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "image arrays disagree with its size ", image.width_px, "x", image.height_px, ": ",
        image.rgb.size(), " rgb, ", image.depth_m.size(), " depth, ", image.normal.size(),
        " normal, ", image.uncertainty.size(), " uncertainty values"));
  }
  return absl::OkStatus();
}

}  // namespace

float LinearToSrgb(float linear) {
  if (!(linear > 0.0f)) return 0.0f;  // also NaN
  if (linear >= 1.0f) return 1.0f;
  if (linear <= 0.0031308f) return 12.92f * linear;
  return 1.055f * std::pow(linear, 1.0f / 2.4f) - 0.055f;
}

absl::StatusOr<std::string> EncodeExr(const RenderImage& image) {
  if (absl::Status s = ValidateImage(image); !s.ok()) return s;
  const int w = image.width_px;
  const int h = image.height_px;
  std::string bytes;
  try {
    // Coverage (§8): images made before the alpha channel existed count every hit as covered.
    std::vector<float> alpha = image.alpha;
    if (alpha.size() != image.depth_m.size()) {
      alpha.assign(image.depth_m.size(), 0.0f);
      for (size_t i = 0; i < alpha.size(); ++i) alpha[i] = std::isfinite(image.depth_m[i]) ? 1.0f : 0.0f;
    }
    Imf::Header header(w, h);  // data window (0,0)-(w-1,h-1)
    header.compression() = Imf::ZIP_COMPRESSION;
    header.lineOrder() = Imf::INCREASING_Y;  // row 0 = top
    struct Plane {
      const char* name;
      const float* base;
      size_t stride;  ///< floats per pixel
    };
    const Plane planes[] = {
        {"R", image.rgb.data() + 0, 3},    {"G", image.rgb.data() + 1, 3},
        {"B", image.rgb.data() + 2, 3},    {"Z", image.depth_m.data(), 1},
        {"N.x", image.normal.data() + 0, 3}, {"N.y", image.normal.data() + 1, 3},
        {"N.z", image.normal.data() + 2, 3}, {"U", image.uncertainty.data(), 1},
        {"A", alpha.data(), 1},
    };
    Imf::FrameBuffer frame;
    for (const Plane& p : planes) {
      header.channels().insert(p.name, Imf::Channel(Imf::FLOAT));
      // OpenEXR's Slice takes a mutable pointer; writing only reads through it.
      frame.insert(p.name, Imf::Slice(Imf::FLOAT, const_cast<char*>(
                                          reinterpret_cast<const char*>(p.base)),
                                      p.stride * sizeof(float), p.stride * sizeof(float) * w));
    }
    StringOStream stream(&bytes);
    Imf::OutputFile file(stream, header);
    file.setFrameBuffer(frame);
    file.writePixels(h);
  } catch (const std::exception& e) {
    return absl::InternalError(absl::StrCat("OpenEXR failed to encode the render: ", e.what()));
  }
  return bytes;
}

absl::StatusOr<std::string> EncodeDeepExr(const RenderImage& image) {
  if (absl::Status s = ValidateImage(image); !s.ok()) return s;
  const int w = image.width_px;
  const int h = image.height_px;
  const size_t pixels = size_t(w) * size_t(h);
  const size_t L = size_t(std::max(1, image.layers));
  const bool deep = L > 1;
  if (deep && (image.layer_count.size() != pixels || image.deep_depth_m.size() != pixels * L ||
               image.deep_rgb.size() != 3 * pixels * L || image.deep_alpha.size() != pixels * L)) {
    return absl::InvalidArgumentError("the image's layer arrays disagree with its size and layers");
  }
  // Samples front to back, packed per pixel: R, G, B, A, Z each in its own array.
  std::vector<unsigned int> count(pixels, 0);
  std::vector<size_t> first(pixels + 1, 0);
  for (size_t p = 0; p < pixels; ++p) {
    count[p] = deep ? image.layer_count[p] : (std::isfinite(image.depth_m[p]) ? 1u : 0u);
    first[p + 1] = first[p] + count[p];
  }
  const size_t total = first[pixels];
  std::vector<float> r(total), g(total), b(total), a(total), z(total);
  for (size_t p = 0; p < pixels; ++p) {
    for (size_t s = 0; s < count[p]; ++s) {
      const size_t o = first[p] + s;
      const size_t q = deep ? p * L + s : p;
      const float* rgb = deep ? &image.deep_rgb[3 * q] : &image.rgb[3 * p];
      r[o] = rgb[0];
      g[o] = rgb[1];
      b[o] = rgb[2];
      a[o] = deep ? image.deep_alpha[q]
                  : (image.alpha.size() == pixels ? image.alpha[p] : 1.0f);
      z[o] = deep ? image.deep_depth_m[q] : image.depth_m[p];
    }
  }
  std::string bytes;
  try {
    Imf::Header header(w, h);
    header.setType(Imf::DEEPSCANLINE);
    header.compression() = Imf::ZIPS_COMPRESSION;
    header.lineOrder() = Imf::INCREASING_Y;
    const std::pair<const char*, std::vector<float>*> planes[] = {
        {"R", &r}, {"G", &g}, {"B", &b}, {"A", &a}, {"Z", &z}};
    std::vector<std::vector<char*>> pointers;
    Imf::DeepFrameBuffer frame;
    frame.insertSampleCountSlice(Imf::Slice(Imf::UINT, reinterpret_cast<char*>(count.data()),
                                            sizeof(unsigned int), sizeof(unsigned int) * w));
    for (const auto& [name, values] : planes) {
      header.channels().insert(name, Imf::Channel(Imf::FLOAT));
      std::vector<char*>& ptr = pointers.emplace_back(pixels);
      for (size_t p = 0; p < pixels; ++p) {
        ptr[p] = reinterpret_cast<char*>(values->data() + first[p]);
      }
      frame.insert(name, Imf::DeepSlice(Imf::FLOAT, reinterpret_cast<char*>(ptr.data()),
                                        sizeof(char*), sizeof(char*) * w, sizeof(float)));
    }
    StringOStream stream(&bytes);
    Imf::DeepScanLineOutputFile file(stream, header);
    file.setFrameBuffer(frame);
    file.writePixels(h);
  } catch (const std::exception& e) {
    return absl::InternalError(absl::StrCat("OpenEXR failed to encode the deep render: ", e.what()));
  }
  return bytes;
}

absl::StatusOr<std::string> EncodePng(const RenderImage& image) {
  if (absl::Status s = ValidateImage(image); !s.ok()) return s;
  const size_t pixels = static_cast<size_t>(image.width_px) * image.height_px;
  // RGBA: alpha 0 where the ray hit nothing or a vossel without colour, whose RGB is the
  // neutral grey 128 (a viewer shows it as transparent; one that ignores alpha, as grey).
  const bool has_alpha = image.alpha.size() == pixels;
  std::vector<uint8_t> srgb(4 * pixels);
  for (size_t p = 0; p < pixels; ++p) {
    const bool covered = has_alpha ? image.alpha[p] > 0.0f : std::isfinite(image.depth_m[p]);
    const bool colourless = !covered && std::isfinite(image.depth_m[p]);
    for (int c = 0; c < 3; ++c) {
      srgb[4 * p + c] = colourless ? uint8_t{128}
                        : !covered ? uint8_t{0}
                                   : static_cast<uint8_t>(std::lround(
                                         LinearToSrgb(image.rgb[3 * p + c]) * 255.0f));
    }
    srgb[4 * p + 3] = covered ? 255 : 0;
  }
  std::vector<unsigned char> bytes;
  OIIO::Filesystem::IOVecOutput proxy(bytes);
  std::unique_ptr<OIIO::ImageOutput> out = OIIO::ImageOutput::create("png");
  if (!out) {
    return absl::InternalError(
        absl::StrCat("OpenImageIO has no PNG writer: ", OIIO::geterror()));
  }
  if (!out->supports("ioproxy") || !out->set_ioproxy(&proxy)) {
    return absl::InternalError("OpenImageIO's PNG writer cannot write to memory (no ioproxy)");
  }
  OIIO::ImageSpec spec(image.width_px, image.height_px, 4, OIIO::TypeDesc::UINT8);
  spec.alpha_channel = 3;
  if (!out->open("render.png", spec) || !out->write_image(OIIO::TypeDesc::UINT8, srgb.data()) ||
      !out->close()) {
    return absl::InternalError(
        absl::StrCat("OpenImageIO failed to encode the PNG: ", out->geterror()));
  }
  return std::string(bytes.begin(), bytes.end());
}

}  // namespace vasl::render

// Test images written as a rig writes them: linear pixels as 8-bit sRGB codes in a JPEG (at a
// chosen quality and chroma subsampling) or a PNG, through OpenImageIO.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>
#include <gtest/gtest.h>

#include "lattice/geometry/linear_image.h"

namespace vasl {
namespace {

/// `img` encoded as 8-bit sRGB in `format` ("jpg" at `quality` with `subsampling` chroma, or
/// "png"); a one-channel image as grey.
std::string EncodeSrgb8(const geometry::LinearImage& img, const char* format, int quality,
                   const char* subsampling = "4:2:0") {
  std::vector<uint8_t> codes(img.pixels.size());
  for (size_t i = 0; i < codes.size(); ++i) {
    const double l = std::clamp(double(img.pixels[i]), 0.0, 1.0);
    const double v = l <= 0.0031308 ? 12.92 * l : 1.055 * std::pow(l, 1.0 / 2.4) - 0.055;
    codes[i] = uint8_t(std::lround(255.0 * v));
  }
  std::vector<unsigned char> bytes;
  OIIO::Filesystem::IOVecOutput proxy(bytes);
  std::unique_ptr<OIIO::ImageOutput> out = OIIO::ImageOutput::create(format);
  EXPECT_TRUE(out && out->set_ioproxy(&proxy));
  OIIO::ImageSpec spec(img.width_px, img.height_px, img.channels, OIIO::TypeDesc::UINT8);
  if (std::string(format) == "jpg") {
    spec.attribute("Compression", "jpeg:" + std::to_string(quality));
    if (img.channels == 3) spec.attribute("jpeg:subsampling", subsampling);
  }
  EXPECT_TRUE(out->open(std::string("image.") + format, spec));
  EXPECT_TRUE(out->write_image(OIIO::TypeDesc::UINT8, codes.data()));
  EXPECT_TRUE(out->close());
  return std::string(bytes.begin(), bytes.end());
}

}  // namespace
}  // namespace vasl

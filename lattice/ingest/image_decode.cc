#include <algorithm>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <random>

#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include "absl/strings/str_cat.h"
#include "lattice/ingest/image_memory.h"
#include "lattice/ingest/sources.h"

namespace vasl::ingest {
namespace {

// The sRGB EOTF (IEC 61966-2-1), encoded [0,1] → linear.
float SrgbToLinear(float c) {
  return c <= 0.04045f ? c / 12.92f : std::pow((c + 0.055f) / 1.055f, 2.4f);
}

// A file-name extension OpenImageIO can pick a reader by, from the magic bytes.
const char* SniffExtension(std::string_view b) {
  auto starts = [&b](std::string_view magic) {
    return b.size() >= magic.size() && b.substr(0, magic.size()) == magic;
  };
  if (starts("\x89PNG")) return ".png";
  if (starts("\xFF\xD8\xFF")) return ".jpg";
  if (starts(std::string_view("\x76\x2f\x31\x01", 4))) return ".exr";
  if (starts(std::string_view("II*\0", 4)) || starts(std::string_view("MM\0*", 4))) return ".tif";
  return nullptr;
}

}  // namespace

namespace internal {

absl::StatusOr<MemoryImageInput> OpenImageInMemory(std::string_view bytes, bool unassociated_alpha,
                                                   int64_t max_pixels) {
  using namespace OIIO;
  const char* ext = SniffExtension(bytes);
  if (ext == nullptr) {
    return absl::InvalidArgumentError(
        "image bytes are not PNG, JPEG, EXR or TIFF (unrecognised signature)");
  }
  if (std::string_view(ext) == ".exr") {
    if (absl::Status header = CheckExrHeaders(bytes, max_pixels); !header.ok()) return header;
  }
  // OpenImageIO reads these formats from memory through an IOProxy.
  MemoryImageInput out;
  out.reader = std::make_unique<Filesystem::IOMemReader>(const_cast<char*>(bytes.data()), bytes.size());
  ImageSpec config;
  // The attribute holds the proxy pointer itself: pass the address of a pointer.
  Filesystem::IOProxy* proxy = out.reader.get();
  config.attribute("oiio:ioproxy", TypeDesc::PTR, &proxy);
  if (unassociated_alpha) config.attribute("oiio:UnassociatedAlpha", 1);
  out.in = ImageInput::open(std::string("memory") + ext, &config);
  if (!out.in) {
    return absl::InvalidArgumentError(
        absl::StrCat("image bytes do not decode as ", ext + 1, ": ", OIIO::geterror()));
  }
  return out;
}

}  // namespace internal

namespace {

// What DecodeImage checks of a header before it allocates (see ProbeImage).
absl::Status CheckSpec(const OIIO::ImageSpec& spec, int64_t max_pixels) {
  if (spec.width <= 0 || spec.height <= 0 || spec.nchannels <= 0) {
    return absl::InvalidArgumentError("decoded image is empty");
  }
  if (spec.nchannels > 16) {  // the decode buffer is width × height × channels floats
    return absl::ResourceExhaustedError(absl::StrCat("image has ", spec.nchannels,
                                                     " channels; at most 16 are decoded"));
  }
  if (int64_t(spec.width) * spec.height > max_pixels) {
    return absl::ResourceExhaustedError(absl::StrCat("image of ", spec.width, "x", spec.height,
                                                     " pixels exceeds the limit of ", max_pixels));
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<ImageHeader> ProbeImage(std::string_view bytes, int64_t max_pixels) {
  absl::StatusOr<internal::MemoryImageInput> opened =
      internal::OpenImageInMemory(bytes, /*unassociated_alpha=*/false, max_pixels);
  if (!opened.ok()) return opened.status();
  const OIIO::ImageSpec& spec = opened->in->spec();
  if (absl::Status s = CheckSpec(spec, max_pixels); !s.ok()) return s;
  return ImageHeader{spec.width, spec.height, spec.nchannels};
}

absl::StatusOr<LinearImage> DecodeImage(std::string_view bytes, bool single_channel,
                                        int64_t max_pixels) {
  using namespace OIIO;
  absl::StatusOr<internal::MemoryImageInput> opened =
      internal::OpenImageInMemory(bytes, /*unassociated_alpha=*/false, max_pixels);
  if (!opened.ok()) return opened.status();
  ImageInput* in = opened->in.get();
  const ImageSpec& spec = in->spec();
  if (absl::Status s = CheckSpec(spec, max_pixels); !s.ok()) return s;
  const bool is_float = spec.format.basetype == TypeDesc::FLOAT ||
                        spec.format.basetype == TypeDesc::HALF ||
                        spec.format.basetype == TypeDesc::DOUBLE;
  const std::string color_space = spec.get_string_attribute("oiio:ColorSpace");
  const bool linear_already = is_float || color_space == "Linear" || color_space == "linear";
  // Integer images are read as their own integers and linearised through a table of every
  // code (2⁸ or 2¹⁶ entries): the sRGB EOTF once per code instead of once per pixel channel.
  const bool int8 = !linear_already && (spec.format.basetype == TypeDesc::UINT8 ||
                                        spec.format.basetype == TypeDesc::INT8);
  const bool int16 = !linear_already && !int8;
  const TypeDesc read_as = int8 ? TypeDesc::UINT8 : int16 ? TypeDesc::UINT16 : TypeDesc::FLOAT;
  const size_t n = size_t(spec.width) * spec.height;
  const int nc = spec.nchannels;
  std::vector<unsigned char> all(n * nc * read_as.size());
  if (!in->read_image(0, 0, 0, nc, read_as, all.data())) {
    return absl::InvalidArgumentError(
        absl::StrCat("image bytes do not decode: ", in->geterror()));
  }
  in->close();
  std::vector<float> table;
  if (!linear_already) {
    const int codes = int8 ? 256 : 65536;
    table.resize(size_t(codes));
    for (int i = 0; i < codes; ++i) table[size_t(i)] = SrgbToLinear(float(i) / float(codes - 1));
  }

  LinearImage out;
  out.width_px = spec.width;
  out.height_px = spec.height;
  out.channels = single_channel ? 1 : 3;
  out.clip_value = is_float ? 0.0f : 1.0f;
  out.pixels.resize(n * out.channels);
  const int oc = out.channels;
  tbb::parallel_for(tbb::blocked_range<size_t>(0, n, 1 << 14), [&](const tbb::blocked_range<size_t>& r) {
    for (size_t p = r.begin(); p != r.end(); ++p) {
      for (int c = 0; c < oc; ++c) {
        const size_t at = p * nc + (nc >= 3 ? c : 0);  // gray (± alpha) is replicated
        float v;
        if (int8) {
          v = table[all[at]];
        } else if (int16) {
          uint16_t code;
          std::memcpy(&code, &all[2 * at], 2);
          v = table[code];
        } else {
          std::memcpy(&v, &all[4 * at], 4);
        }
        out.pixels[p * oc + c] = v;
      }
    }
  });
  return out;
}

}  // namespace vasl::ingest

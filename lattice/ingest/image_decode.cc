#include <algorithm>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <memory>
#include <random>

#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_reduce.h>

#include "absl/strings/str_cat.h"
#include "lattice/ingest/image_memory.h"
#include "lattice/ingest/sources.h"
#include "lattice/memory/buffer_pool.h"
#include "lattice/memory/huge_pages.h"

namespace vasl::ingest {
namespace {

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

/// The JPEG zigzag order: the natural (row-major) index of the k-th coefficient a file lists.
constexpr int kZigzag[64] = {0,  1,  8,  16, 9,  2,  3,  10, 17, 24, 32, 25, 18, 11, 4,  5,
                             12, 19, 26, 33, 40, 48, 41, 34, 27, 20, 13, 6,  7,  14, 21, 28,
                             35, 42, 49, 56, 57, 50, 43, 36, 29, 22, 15, 23, 30, 37, 44, 51,
                             58, 59, 52, 45, 38, 31, 39, 46, 53, 60, 61, 54, 47, 55, 62, 63};

}  // namespace

std::shared_ptr<const geometry::BlockCoding> ReadJpegCoding(std::string_view b) {
  if (b.size() < 4 || uint8_t(b[0]) != 0xFF || uint8_t(b[1]) != 0xD8) return nullptr;
  std::array<std::array<uint16_t, 64>, 4> tables{};
  std::array<bool, 4> have{};
  int luma_table = -1, chroma_table = -1, h_max = 1, v_max = 1, h_c = 1, v_c = 1;
  size_t at = 2;
  auto byte = [&](size_t i) { return int(uint8_t(b[i])); };
  while (at + 4 <= b.size()) {
    if (byte(at) != 0xFF) return nullptr;  // not a marker where one must be
    const int marker = byte(at + 1);
    if (marker == 0xFF) {  // fill byte
      ++at;
      continue;
    }
    if (marker == 0xD8 || marker == 0x01 || (marker >= 0xD0 && marker <= 0xD7)) {
      at += 2;
      continue;
    }
    const size_t length = size_t(byte(at + 2) << 8 | byte(at + 3));
    if (length < 2 || at + 2 + length > b.size()) return nullptr;
    const size_t body = at + 4, end = at + 2 + length;
    if (marker == 0xDB) {  // DQT: tables of 64 steps in zigzag order, 8- or 16-bit
      for (size_t i = body; i < end;) {
        const int precision = byte(i) >> 4, id = byte(i) & 0x0F;
        const size_t size = precision ? 128 : 64;
        if (id > 3 || i + 1 + size > end) return nullptr;
        for (int k = 0; k < 64; ++k) {
          tables[size_t(id)][size_t(kZigzag[k])] = uint16_t(
              precision ? byte(i + 1 + 2 * size_t(k)) << 8 | byte(i + 2 + 2 * size_t(k))
                        : byte(i + 1 + size_t(k)));
        }
        have[size_t(id)] = true;
        i += 1 + size;
      }
    } else if (marker >= 0xC0 && marker <= 0xCF && marker != 0xC4 && marker != 0xC8 &&
               marker != 0xCC) {  // SOFn: components, their sampling and tables
      if (marker != 0xC0 && marker != 0xC1 && marker != 0xC2) return nullptr;  // DCT, Huffman
      if (body + 6 > end) return nullptr;
      const int components = byte(body + 5);
      if (body + 6 + 3 * size_t(components) > end) return nullptr;
      for (int c = 0; c < components; ++c) {
        const size_t o = body + 6 + 3 * size_t(c);
        const int h = byte(o + 1) >> 4, v = byte(o + 1) & 0x0F, table = byte(o + 2) & 0x03;
        h_max = std::max(h_max, h), v_max = std::max(v_max, v);
        if (c == 0) luma_table = table;
        if (c == 1) chroma_table = table, h_c = std::max(1, h), v_c = std::max(1, v);
      }
      if (components == 1) chroma_table = luma_table;
    } else if (marker == 0xDA) {  // SOS: the tables in force are known
      break;
    }
    at = end;
  }
  if (luma_table < 0 || !have[size_t(luma_table)]) return nullptr;
  auto coding = std::make_shared<geometry::BlockCoding>();
  coding->luma_q = tables[size_t(luma_table)];
  coding->chroma_q = chroma_table >= 0 && have[size_t(chroma_table)]
                         ? tables[size_t(chroma_table)]
                         : coding->luma_q;
  coding->chroma_step_x = std::max(1, h_max / h_c);
  coding->chroma_step_y = std::max(1, v_max / v_c);
  for (uint16_t q : coding->luma_q) {
    if (q == 0) return nullptr;
  }
  for (uint16_t q : coding->chroma_q) {
    if (q == 0) return nullptr;
  }
  return coding;
}

namespace internal {

size_t BoundedMemReader::read(void* buf, size_t size) {
  const size_t n = pread(buf, size, m_pos);
  m_pos += int64_t(n);
  return n;
}

size_t BoundedMemReader::pread(void* buf, size_t size, int64_t offset) {
  if (offset < 0 || uint64_t(offset) >= m_buf.size()) return 0;
  const size_t n = std::min(size, m_buf.size() - size_t(offset));
  std::memcpy(buf, m_buf.data() + offset, n);
  return n;
}

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
  out.reader = std::make_unique<BoundedMemReader>(bytes.data(), bytes.size());
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

// Integer code `at` of 8-bit (`int8`) or 16-bit native-endian `codes` as a linear share of its
// full scale, code / 255 or code / 65535: how alpha and mask codes are read (never sRGB).
float ShareOfCode(const unsigned char* codes, size_t at, bool int8) {
  if (int8) return float(codes[at]) / 255.0f;
  uint16_t code;
  std::memcpy(&code, &codes[2 * at], 2);
  return float(code) / 65535.0f;
}

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

absl::StatusOr<LinearImage> DecodeImage(std::string_view bytes, bool infrared,
                                        int64_t max_pixels) {
  using namespace OIIO;
  // Colour beside an alpha channel is read as the file keeps it (unassociated in a PNG or most
  // TIFFs, associated in an EXR), and associated here after linearisation.
  absl::StatusOr<internal::MemoryImageInput> opened =
      internal::OpenImageInMemory(bytes, /*unassociated_alpha=*/true, max_pixels);
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
  std::vector<unsigned char> all;
  memory::AssignOnHugePages(all, n * nc * read_as.size(), static_cast<unsigned char>(0));
  if (!in->read_image(0, 0, 0, nc, read_as, all.data())) {
    return absl::InvalidArgumentError(
        absl::StrCat("image bytes do not decode: ", in->geterror()));
  }
  in->close();
  std::vector<float> table;
  if (int8) {
    table.assign(geometry::Srgb8ToLinear().begin(), geometry::Srgb8ToLinear().end());
  } else if (int16) {
    table.resize(65536);
    for (int i = 0; i < 65536; ++i) {
      const float code = float(i) / 65535.0f;  // an infrared camera's radiometric counts
      table[size_t(i)] = infrared ? code : geometry::SrgbToLinear(code);
    }
  }

  LinearImage out;
  out.width_px = spec.width;
  out.height_px = spec.height;
  out.channels = infrared ? 1 : 3;
  out.clip_value = is_float ? 0.0f : 1.0f;
  if (int8) out.coding = ReadJpegCoding(bytes);  // §9 codec: what the JPEG's coding did
  out.pixels = memory::TakeFloatsForOverwrite(n * out.channels);  // every value written below
  const int oc = out.channels;
  // The colour channels: the first three that are not alpha (one, gray, is replicated).
  const int alpha_at = nc > 1 && spec.alpha_channel >= 0 && spec.alpha_channel < nc
                           ? spec.alpha_channel
                           : -1;
  int colour_at[3] = {0, 0, 0};
  {
    int found = 0;
    for (int c = 0; c < nc && found < 3; ++c) {
      if (c != alpha_at) colour_at[found++] = c;
    }
    if (found < 3) colour_at[1] = colour_at[2] = colour_at[0];
  }
  // Alpha is a linear share, never sRGB: integer codes over their full scale.
  const bool associated = spec.get_int_attribute("oiio:UnassociatedAlpha", 0) == 0;
  auto value_at = [&](size_t at, bool linear) {
    if (linear && (int8 || int16)) return ShareOfCode(all.data(), at, int8);
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
    return v;
  };
  std::vector<float> alpha;
  if (alpha_at >= 0) alpha = memory::TakeFloatsForOverwrite(n);  // every value written below
  const bool covered_whole = tbb::parallel_reduce(
      tbb::blocked_range<size_t>(0, n, 1 << 14), true,
      [&](const tbb::blocked_range<size_t>& r, bool whole) {
        for (size_t p = r.begin(); p != r.end(); ++p) {
          float a = 1.0f;
          if (alpha_at >= 0) {
            const float read = value_at(p * nc + size_t(alpha_at), /*linear=*/true);
            a = std::isnan(read) ? 0.0f : std::clamp(read, 0.0f, 1.0f);
            alpha[p] = a;
            whole = whole && a == 1.0f;
          }
          for (int c = 0; c < oc; ++c) {
            const float v = value_at(p * nc + size_t(colour_at[c]), /*linear=*/false);
            out.pixels[p * oc + c] = associated || a == 1.0f ? v : v * a;
          }
        }
        return whole;
      },
      [](bool a, bool b) { return a && b; });
  if (alpha_at >= 0 && !covered_whole) out.alpha = std::move(alpha);
  memory::GiveFloats(std::move(alpha));  // a whole cover's (or none)
  return out;
}

absl::Status ApplyMask(std::string_view mask_bytes, int64_t max_pixels, LinearImage& image) {
  using namespace OIIO;
  absl::StatusOr<internal::MemoryImageInput> opened =
      internal::OpenImageInMemory(mask_bytes, /*unassociated_alpha=*/true, max_pixels);
  if (!opened.ok()) {
    return absl::Status(opened.status().code(),
                        absl::StrCat("mask: ", opened.status().message()));
  }
  ImageInput* in = opened->in.get();
  const ImageSpec& spec = in->spec();
  if (absl::Status s = CheckSpec(spec, max_pixels); !s.ok()) {
    return absl::Status(s.code(), absl::StrCat("mask: ", s.message()));
  }
  if (spec.width != image.width_px || spec.height != image.height_px) {
    return absl::InvalidArgumentError(absl::StrCat("mask is ", spec.width, "x", spec.height,
                                                   ", not the image's ", image.width_px, "x",
                                                   image.height_px));
  }
  const size_t n = size_t(spec.width) * spec.height;
  std::vector<float> mask;
  memory::AssignOnHugePages(mask, n, 0.0f);
  // Integer codes are read as code / full scale, linearly (a mask is no colour), as DecodeImage
  // reads alpha codes: a mask and the same codes as the image's alpha give the same image.
  const TypeDesc::BASETYPE base = TypeDesc::BASETYPE(spec.format.basetype);
  const bool int8 = base == TypeDesc::UINT8 || base == TypeDesc::INT8;
  const bool int16 = base == TypeDesc::UINT16 || base == TypeDesc::INT16;
  std::vector<unsigned char> codes(int8 ? n : int16 ? 2 * n : 0);
  const bool read =
      int8    ? in->read_image(0, 0, 0, 1, TypeDesc::UINT8, codes.data())
      : int16 ? in->read_image(0, 0, 0, 1, TypeDesc::UINT16, codes.data())
              : in->read_image(0, 0, 0, 1, TypeDesc::FLOAT, mask.data());
  if (!read) {
    return absl::InvalidArgumentError(absl::StrCat("mask bytes do not decode: ", in->geterror()));
  }
  in->close();
  if (int8 || int16) {
    tbb::parallel_for(tbb::blocked_range<size_t>(0, n, 1 << 16), [&](const tbb::blocked_range<size_t>& r) {
      for (size_t p = r.begin(); p != r.end(); ++p) mask[p] = ShareOfCode(codes.data(), p, int8);
    });
  }
  const float largest = tbb::parallel_reduce(
      tbb::blocked_range<size_t>(0, n, 1 << 16), 0.0f,
      [&](const tbb::blocked_range<size_t>& r, float m) {
        for (size_t p = r.begin(); p != r.end(); ++p) m = std::max(m, mask[p]);  // NaN ignored
        return m;
      },
      [](float a, float b) { return std::max(a, b); });
  const bool whole = tbb::parallel_reduce(
      tbb::blocked_range<size_t>(0, n, 1 << 16), true,
      [&](const tbb::blocked_range<size_t>& r, bool all) {
        for (size_t p = r.begin(); p != r.end(); ++p) {
          const float m = largest > 0.0f ? mask[p] / largest : 0.0f;
          mask[p] = m >= 0.0f ? std::min(m, 1.0f) : 0.0f;  // NaN and negatives: not reported
          all = all && mask[p] == 1.0f;
        }
        return all;
      },
      [](bool a, bool b) { return a && b; });
  if (whole) return absl::OkStatus();
  if (image.alpha.empty()) memory::AssignOnHugePages(image.alpha, n, 1.0f);
  const int c = image.channels;
  tbb::parallel_for(tbb::blocked_range<size_t>(0, n, 1 << 14), [&](const tbb::blocked_range<size_t>& r) {
    for (size_t p = r.begin(); p != r.end(); ++p) {
      if (mask[p] == 1.0f) continue;
      image.alpha[p] *= mask[p];
      for (int k = 0; k < c; ++k) image.pixels[p * c + size_t(k)] *= mask[p];
    }
  });
  return absl::OkStatus();
}

absl::Status CheckSphereWindow(const SphereWindow& window, int width_px, int height_px) {
  const SphereWindow& w = window;
  const double aspect = w.height_px > 0 ? double(w.width_px) / w.height_px : 0.0;
  if (w.width_px <= 0 || w.height_px <= 0 || aspect < 1.95 || aspect > 2.05) {
    return absl::InvalidArgumentError(absl::StrCat(
        "its sphere is ", w.width_px, "x", w.height_px, ": the whole sphere's panorama spans "
        "360°×180°, so its width must be twice its height"));
  }
  if (w.left_px < 0 || w.top_px < 0 || int64_t(w.left_px) + width_px > w.width_px ||
      int64_t(w.top_px) + height_px > w.height_px) {
    return absl::InvalidArgumentError(absl::StrCat(
        "the ", width_px, "x", height_px, " image at (", w.left_px, ", ", w.top_px,
        ") does not lie within its ", w.width_px, "x", w.height_px, " sphere"));
  }
  return absl::OkStatus();
}

absl::Status PlaceInSphere(const SphereWindow& window, int64_t max_pixels, LinearImage& image) {
  if (absl::Status s = CheckSphereWindow(window, image.width_px, image.height_px); !s.ok()) {
    return s;
  }
  const int64_t pixels = int64_t(window.width_px) * window.height_px;
  if (pixels > max_pixels) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "its ", window.width_px, "x", window.height_px, " sphere has ", pixels,
        " pixels, above the limit of ", max_pixels));
  }
  const int W = window.width_px, H = window.height_px, w = image.width_px, h = image.height_px;
  if (w == W && h == H) return absl::OkStatus();  // the whole sphere already
  const size_t C = size_t(image.channels);
  LinearImage out;
  out.width_px = W;
  out.height_px = H;
  out.channels = image.channels;
  out.clip_value = image.clip_value;
  out.coding = image.coding;
  out.coded_window = geometry::ImageWindow{window.left_px, window.top_px, w, h};
  memory::AssignOnHugePages(out.pixels, size_t(pixels) * C, 0.0f);
  memory::AssignOnHugePages(out.alpha, size_t(pixels), 0.0f);
  tbb::parallel_for(tbb::blocked_range<int>(0, h, 16), [&](const tbb::blocked_range<int>& rows) {
    for (int j = rows.begin(); j != rows.end(); ++j) {
      const size_t from = size_t(j) * size_t(w), to = size_t(j + window.top_px) * size_t(W) +
                                                    size_t(window.left_px);
      std::copy_n(&image.pixels[from * C], size_t(w) * C, &out.pixels[to * C]);
      if (image.alpha.empty()) {
        std::fill_n(&out.alpha[to], size_t(w), 1.0f);
      } else {
        std::copy_n(&image.alpha[from], size_t(w), &out.alpha[to]);
      }
    }
  });
  image = std::move(out);
  return absl::OkStatus();
}

absl::StatusOr<CylinderPlacement> CylinderWindow(const CylinderImage& c, int width_px,
                                                 int height_px) {
  if (!(c.pixel_width_rad > 0.0 && c.pixel_width_rad <= 0.1) ||
      !(c.pixel_height_m > 0.0 && std::isfinite(c.pixel_height_m)) ||
      !(c.radius_m > 0.0 && std::isfinite(c.radius_m)) || !std::isfinite(c.principal_y_px)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "a cylinder needs pixel_width_rad in (0, 0.1], pixel_height_m and radius_m > 0 and a "
        "finite principal_y_px; got ", c.pixel_width_rad, ", ", c.pixel_height_m, ", ",
        c.radius_m, ", ", c.principal_y_px));
  }
  // A sphere of at most 2^20 rows (its pixels are checked against the limit after).
  if (M_PI / c.pixel_width_rad > double(1 << 20)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "a cylinder's pixel_width_rad of ", c.pixel_width_rad,
        " makes a sphere of more than 2^20 rows"));
  }
  const int rows = std::max(1, int(std::lround(M_PI / c.pixel_width_rad)));
  const int columns = 2 * rows;
  if (width_px > columns) {
    return absl::InvalidArgumentError(absl::StrCat(
        "the cylindrical image's ", width_px, " columns of ", c.pixel_width_rad,
        " rad span more than 360°"));
  }
  const double pitch = M_PI / rows;
  const double top = std::atan(c.principal_y_px * c.pixel_height_m / c.radius_m);
  const double bottom = std::atan((c.principal_y_px - height_px) * c.pixel_height_m / c.radius_m);
  // The sphere's row j has its centre at elevation π/2 − (j + 0.5)·pitch (§2.1).
  const int j0 = std::max(0, int(std::ceil((M_PI / 2 - top) / pitch - 0.5)));
  const int j1 = std::min(rows - 1, int(std::floor((M_PI / 2 - bottom) / pitch - 0.5)));
  if (j1 < j0) {
    return absl::InvalidArgumentError("the cylindrical image covers no row of the sphere");
  }
  return CylinderPlacement{SphereWindow{columns, rows, (columns - width_px) / 2, j0},
                           j1 - j0 + 1};
}

absl::Status CylinderToSphere(const CylinderImage& c, int64_t max_pixels, LinearImage& image) {
  absl::StatusOr<CylinderPlacement> placed = CylinderWindow(c, image.width_px, image.height_px);
  if (!placed.ok()) return placed.status();
  const SphereWindow& window = placed->window;
  if (int64_t(window.width_px) * window.height_px > max_pixels) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "its ", window.width_px, "x", window.height_px, " sphere has ",
        int64_t(window.width_px) * window.height_px, " pixels, above the limit of ", max_pixels));
  }
  const int w = image.width_px, h = image.height_px, rows = placed->rows;
  const size_t C = size_t(image.channels), row_values = size_t(w) * C;
  LinearImage out;
  out.width_px = w;
  out.height_px = rows;
  out.channels = image.channels;
  out.clip_value = image.clip_value;
  memory::AssignOnHugePages(out.pixels, size_t(rows) * row_values, 0.0f);
  if (!image.alpha.empty()) memory::AssignOnHugePages(out.alpha, size_t(rows) * size_t(w), 0.0f);
  const double pitch = M_PI / window.height_px;
  tbb::parallel_for(tbb::blocked_range<int>(0, rows, 16), [&](const tbb::blocked_range<int>& r) {
    for (int k = r.begin(); k != r.end(); ++k) {
      const double psi = M_PI / 2 - (window.top_px + k + 0.5) * pitch;
      // The cylinder's row coordinate at that elevation; its pixel centres lie at i + 0.5.
      const double y = std::clamp(
          c.principal_y_px - c.radius_m * std::tan(psi) / c.pixel_height_m - 0.5, 0.0,
          double(h - 1));
      const int i0 = int(std::floor(y)), i1 = std::min(i0 + 1, h - 1);
      const float f = float(y - i0), g = 1.0f - f;
      const float* a = &image.pixels[size_t(i0) * row_values];
      const float* b = &image.pixels[size_t(i1) * row_values];
      float* o = &out.pixels[size_t(k) * row_values];
      for (size_t v = 0; v < row_values; ++v) o[v] = g * a[v] + f * b[v];
      if (!image.alpha.empty()) {
        const float* aa = &image.alpha[size_t(i0) * size_t(w)];
        const float* ba = &image.alpha[size_t(i1) * size_t(w)];
        float* oa = &out.alpha[size_t(k) * size_t(w)];
        for (int i = 0; i < w; ++i) oa[i] = g * aa[i] + f * ba[i];
      }
    }
  });
  image = std::move(out);  // resampled: no codec blocks, no coded window
  return PlaceInSphere(window, max_pixels, image);
}

}  // namespace vasl::ingest

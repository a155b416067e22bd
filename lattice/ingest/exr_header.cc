// A strict walk over an OpenEXR file's headers before OpenEXR reads them (image_memory.h).
//
// OpenEXR 3.1 reads a header attribute by its type, not by its size field: an attribute of an
// unknown type allocates the size it claims before reading it (the fuzzer's 16-byte file made it
// allocate 2 GiB), and a channel list reads entries until an empty name whatever its size says,
// so a size that disagrees with the content puts OpenEXR out of step with the bytes and on to
// whatever the following bytes claim. The offset table is then sized from the data window and
// the tiling. This walk reads every attribute as OpenEXR will, demands that each consumes
// exactly the size it declares, and that the chunk offsets the headers imply fit in the bytes
// that follow: every allocation the headers can cause is then bounded by the bytes sent.
#include <algorithm>
#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "lattice/ingest/image_memory.h"

namespace vasl::ingest::internal {
namespace {

constexpr uint32_t kTiledFlag = 0x200;
constexpr uint32_t kLongNamesFlag = 0x400;
constexpr uint32_t kMultipartFlag = 0x1000;

int32_t ReadInt32(const char* p) {
  const auto* u = reinterpret_cast<const unsigned char*>(p);  // OpenEXR is little-endian
  return int32_t(uint32_t(u[0]) | uint32_t(u[1]) << 8 | uint32_t(u[2]) << 16 | uint32_t(u[3]) << 24);
}

// The byte size of each fixed-size attribute type OpenEXR 3.1 knows (ImfHeader.cpp).
const std::map<std::string, int32_t>& FixedSizes() {
  static const auto* sizes = new std::map<std::string, int32_t>{
      {"box2i", 16},   {"box2f", 16},  {"compression", 1}, {"lineOrder", 1},  {"envmap", 1},
      {"deepImageState", 1}, {"double", 8}, {"float", 4}, {"int", 4},          {"m33f", 36},
      {"m33d", 72},    {"m44f", 64},   {"m44d", 128},      {"rational", 8},   {"tiledesc", 9},
      {"timecode", 8}, {"keycode", 28}, {"v2i", 8},        {"v2f", 8},        {"v2d", 16},
      {"v3i", 12},     {"v3f", 12},    {"v3d", 24},        {"chromaticities", 32}};
  return *sizes;
}

// Scan lines per chunk of each compression (ImfCompression.h order).
int LinesPerChunk(int compression) {
  static constexpr int kLines[] = {1, 1, 1, 16, 32, 16, 32, 32, 32, 256};
  return compression >= 0 && compression < int(std::size(kLines)) ? kLines[compression] : -1;
}

// What the chunk count of a part depends on.
struct Part {
  bool has_window = false;
  int64_t width = 0, height = 0;
  int compression = -1;
  bool has_tiles = false;
  int64_t tile_x = 0, tile_y = 0;
  int level_mode = 0, rounding = 0;
  int64_t chunk_count = -1;
  std::string type;
};

int64_t LevelSize(int64_t n, int l, int rounding) {
  const int64_t b = int64_t(1) << l;
  int64_t size = n / b;
  if (rounding == 1 && size * b < n) size += 1;
  return std::max<int64_t>(size, 1);
}

int Levels(int64_t n, int rounding) {
  int y = 0, r = 0;
  for (; n > 1; n >>= 1, ++y) r |= int(n & 1);
  return (rounding == 1 ? y + r : y) + 1;
}

// The chunks (offset-table entries) of a tiled part: tiles of every level (ImfTiledMisc.cpp).
int64_t TiledChunks(const Part& p) {
  auto tiles = [](int64_t n, int64_t t) { return (n + t - 1) / t; };
  int64_t sum = 0;
  if (p.level_mode == 0) return tiles(p.width, p.tile_x) * tiles(p.height, p.tile_y);
  if (p.level_mode == 1) {
    const int levels = Levels(std::max(p.width, p.height), p.rounding);
    for (int l = 0; l < levels; ++l) {
      sum += tiles(LevelSize(p.width, l, p.rounding), p.tile_x) *
             tiles(LevelSize(p.height, l, p.rounding), p.tile_y);
    }
    return sum;
  }
  const int lx = Levels(p.width, p.rounding), ly = Levels(p.height, p.rounding);
  for (int x = 0; x < lx; ++x) {
    for (int y = 0; y < ly; ++y) {
      sum += tiles(LevelSize(p.width, x, p.rounding), p.tile_x) *
             tiles(LevelSize(p.height, y, p.rounding), p.tile_y);
    }
  }
  return sum;
}

}  // namespace

absl::Status CheckExrHeaders(std::string_view bytes, int64_t max_pixels) {
  auto bad = [](const std::string& why) {
    return absl::InvalidArgumentError(absl::StrCat("the EXR header is malformed: ", why));
  };
  if (bytes.size() < 8) return bad("the file is shorter than its magic number and version");
  const uint32_t version = uint32_t(ReadInt32(bytes.data() + 4));
  if ((version & 0xff) != 2) return bad(absl::StrCat("version ", version & 0xff, " is not 2"));
  const size_t max_name = (version & kLongNamesFlag) ? 255 : 31;
  const bool multipart = (version & kMultipartFlag) != 0;
  const bool single_tiled = (version & kTiledFlag) != 0;
  size_t at = 8;
  // A null-terminated name of 1..max_name characters at `at`; advances past its terminator.
  auto name = [&](size_t end, std::string& out) -> bool {
    const size_t limit = std::min(end, at + max_name + 1);
    for (size_t i = at; i < limit; ++i) {
      if (bytes[i] == '\0') {
        out.assign(bytes.data() + at, i - at);
        at = i + 1;
        return !out.empty();
      }
    }
    return false;
  };
  std::vector<Part> parts;
  while (true) {
    if (at >= bytes.size()) return bad("the header ends before its terminator");
    if (bytes[at] == '\0') {  // an empty header: the end of a multi-part header list
      if (multipart && !parts.empty()) {
        ++at;
        break;
      }
      return bad("a header has no attributes");
    }
    Part& part = parts.emplace_back();
    while (true) {
      if (at >= bytes.size()) return bad("an attribute list ends before its terminator");
      if (bytes[at] == '\0') {
        ++at;
        break;
      }
      std::string attr, type;
      if (!name(bytes.size(), attr)) return bad("an attribute name is unterminated or too long");
      if (!name(bytes.size(), type)) return bad(absl::StrCat("attribute '", attr, "' has a bad type name"));
      if (at + 4 > bytes.size()) return bad("an attribute size is cut off");
      const int32_t size = ReadInt32(bytes.data() + at);
      at += 4;
      if (size < 0 || size_t(size) > bytes.size() - at) {
        return bad(absl::StrCat("attribute '", attr, "' claims ", size, " bytes; ",
                                bytes.size() - at, " remain in the file"));
      }
      const char* value = bytes.data() + at;
      const size_t end = at + size_t(size);
      auto wrong_size = [&] {
        return bad(absl::StrCat("attribute '", attr, "' of type ", type, " declares ", size,
                                " bytes, which its content does not fill exactly"));
      };
      // Read the value as OpenEXR will, and insist that it consumes exactly `size` bytes.
      if (auto fixed = FixedSizes().find(type); fixed != FixedSizes().end()) {
        if (size != fixed->second) return wrong_size();
      } else if (type == "chlist") {  // entries up to an empty name, whatever `size` says
        const size_t start = at;
        while (true) {
          if (at >= end) return wrong_size();
          if (bytes[at] == '\0') {
            ++at;
            break;
          }
          std::string channel;
          if (!name(end, channel) || at + 16 > end) return wrong_size();
          at += 16;  // pixel type, pLinear, 3 reserved bytes, x and y sampling
        }
        if (at != end) return wrong_size();
        at = start;
      } else if (type == "stringvector") {
        for (size_t s = at; s < end;) {
          if (s + 4 > end) return wrong_size();
          const int32_t n = ReadInt32(bytes.data() + s);
          s += 4;
          if (n < 0 || size_t(n) > end - s) return wrong_size();
          s += size_t(n);
        }
      } else if (type == "floatvector") {
        if (size % 4 != 0) return wrong_size();
      } else if (type == "preview") {
        if (size < 8) return wrong_size();
        const int64_t w = ReadInt32(value), h = ReadInt32(value + 4);
        if (w < 0 || h < 0 || w * h * 4 + 8 != size) return wrong_size();
      } else if (type == "idmanifest") {
        if (size < 8) return wrong_size();
      }
      // Any other type ("string", or one OpenEXR does not know) is read as `size` bytes.

      if (attr == "dataWindow" && type == "box2i") {
        const int64_t x0 = ReadInt32(value), y0 = ReadInt32(value + 4);
        const int64_t x1 = ReadInt32(value + 8), y1 = ReadInt32(value + 12);
        part.width = x1 - x0 + 1;
        part.height = y1 - y0 + 1;
        if (part.width <= 0 || part.height <= 0) return bad("the data window is empty");
        if (part.width > max_pixels || part.height > max_pixels ||
            part.width * part.height > max_pixels) {
          return absl::ResourceExhaustedError(absl::StrCat(
              "image of ", part.width, "x", part.height, " pixels exceeds the limit of ", max_pixels));
        }
        part.has_window = true;
      } else if (attr == "compression" && type == "compression") {
        part.compression = static_cast<unsigned char>(value[0]);
      } else if (attr == "tiles" && type == "tiledesc") {
        part.has_tiles = true;
        part.tile_x = int64_t(uint32_t(ReadInt32(value)));
        part.tile_y = int64_t(uint32_t(ReadInt32(value + 4)));
        part.level_mode = static_cast<unsigned char>(value[8]) & 0x0f;
        part.rounding = static_cast<unsigned char>(value[8]) >> 4;
      } else if (attr == "chunkCount" && type == "int") {
        part.chunk_count = ReadInt32(value);
      } else if (attr == "type" && type == "string") {
        part.type.assign(value, size_t(size));
      }
      at = end;
    }
    if (!multipart) break;
  }

  // The offset table: one 8-byte entry per chunk, each of which must be in the file.
  int64_t chunks = 0;
  for (const Part& p : parts) {
    if (!p.has_window) return bad("a header has no dataWindow");
    const int lines = LinesPerChunk(p.compression);
    if (lines < 0) return bad(absl::StrCat("compression ", p.compression, " is unknown"));
    const bool tiled = multipart ? (p.type == "tiledimage" || p.type == "deeptile") : single_tiled;
    int64_t n;
    if (tiled) {
      if (!p.has_tiles) return bad("a tiled part has no tile description");
      if (p.tile_x < 1 || p.tile_y < 1 || p.level_mode > 2 || p.rounding > 1) {
        return bad("the tile description is invalid");
      }
      if (p.tile_x * p.tile_y > std::max<int64_t>(p.width * p.height, 1 << 16)) {
        return bad(absl::StrCat("tiles of ", p.tile_x, "x", p.tile_y,
                                " pixels are larger than the image"));
      }
      n = TiledChunks(p);
    } else {
      n = (p.height + lines - 1) / lines;
    }
    if (p.chunk_count >= 0) n = std::max(n, p.chunk_count);
    if (multipart && p.chunk_count < 0) return bad("a part of a multi-part file has no chunkCount");
    chunks += n;
  }
  if (chunks > int64_t(bytes.size() - at) / 8) {
    return bad(absl::StrCat("the headers imply ", chunks, " chunks, whose offsets alone need more "
                            "than the ", bytes.size() - at, " bytes that follow"));
  }
  return absl::OkStatus();
}

}  // namespace vasl::ingest::internal

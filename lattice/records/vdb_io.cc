#include "lattice/records/vdb_io.h"

#include <cstring>
#include <exception>
#include <fstream>
#include <iterator>
#include <mutex>
#include <sstream>
#include <string>
#include <system_error>

#include <openvdb/io/Archive.h>
#include <openvdb/io/File.h>
#include <openvdb/points/PointDataGrid.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"

namespace vasl::records::internal {

void EnsureOpenVdbInitialized() {
  static std::once_flag once;
  std::call_once(once, [] { openvdb::initialize(); });
}

namespace {

// OpenVDB's header: magic (8 bytes), file version, library major and minor (4 each), a
// has-grid-offsets byte, then the UUID as 36 ASCII characters.
constexpr size_t kUuidAt = 21, kUuidLen = 36;

// OpenVDB's file writer into any seekable stream (io::File::write is this on an ofstream it
// opens on its path).
class StreamArchive : public openvdb::io::Archive {
 public:
  void WriteTo(std::ostream& os, const openvdb::GridCPtrVec& grids,
               const openvdb::MetaMap& meta) const {
    Archive::write(os, grids, /*seekable=*/true, meta);
  }
};

}  // namespace

namespace {

// OpenVDB's compression flags for `compression`.
uint32_t CompressionFlags(VdbCompression compression) {
  uint32_t flags = openvdb::io::COMPRESS_ACTIVE_MASK;
  if (compression == VdbCompression::kBlosc) {
    flags |= openvdb::io::Archive::hasBloscCompression() ? openvdb::io::COMPRESS_BLOSC
                                                         : openvdb::io::COMPRESS_ZIP;
  }
  return flags;
}

}  // namespace

absl::StatusOr<std::string> EncodeVdbFile(const openvdb::GridCPtrVec& grids,
                                          const openvdb::MetaMap& meta,
                                          VdbCompression compression, const std::string& where,
                                          VdbGridStats stats) {
  EnsureOpenVdbInitialized();
  std::string bytes;
  try {
    StreamArchive archive;
    archive.setCompression(CompressionFlags(compression));
    archive.setGridStatsMetadataEnabled(stats == VdbGridStats::kWrite);
    std::stringstream stream(std::ios::in | std::ios::out | std::ios::binary);
    archive.WriteTo(stream, grids, meta);
    bytes = std::move(stream).str();
  } catch (const std::exception& e) {
    return absl::InternalError(absl::StrCat("cannot write ", where, ": ", e.what()));
  }
  if (absl::Status s = MakeUuidDeterministic(bytes, where); !s.ok()) return s;
  return bytes;
}

absl::Status WriteVdbFile(const std::filesystem::path& path, const openvdb::GridCPtrVec& grids,
                          const openvdb::MetaMap& meta, VdbCompression compression) {
  EnsureOpenVdbInitialized();
  // A file of a few tiles is written in memory, its UUID made deterministic there, then to the
  // file in one write: no small writes into fresh pages, and no reading the file back. A large
  // one (a version's export) is written to the file as io::File writes it, so that memory
  // holds it once, not twice.
  constexpr openvdb::Index64 kInMemoryBytes = openvdb::Index64{64} << 20;
  openvdb::Index64 in_core = 0;
  for (const openvdb::GridBase::ConstPtr& grid : grids) in_core += grid ? grid->memUsage() : 0;
  if (in_core <= kInMemoryBytes) {
    absl::StatusOr<std::string> bytes = EncodeVdbFile(grids, meta, compression, path.string());
    if (!bytes.ok()) return bytes.status();
    std::ofstream out(path, std::ios::out | std::ios::binary | std::ios::trunc);
    out.write(bytes->data(), std::streamsize(bytes->size()));
    out.close();
    if (!out) return absl::InternalError(absl::StrCat("cannot write ", path.string()));
    return absl::OkStatus();
  }
  try {
    StreamArchive archive;
    archive.setCompression(CompressionFlags(compression));
    std::ofstream file(path, std::ios::out | std::ios::binary | std::ios::trunc);
    if (!file) return absl::InternalError(absl::StrCat("cannot open ", path.string()));
    archive.WriteTo(file, grids, meta);
    file.close();
    if (!file) return absl::InternalError(absl::StrCat("cannot write ", path.string()));
  } catch (const std::exception& e) {
    return absl::InternalError(absl::StrCat("cannot write ", path.string(), ": ", e.what()));
  }
  // Its UUID fixed in place.
  std::string bytes;
  std::fstream f(path, std::ios::in | std::ios::out | std::ios::binary | std::ios::ate);
  if (!f) return absl::InternalError(absl::StrCat("cannot reopen ", path.string()));
  bytes.resize(size_t(f.tellg()));
  f.seekg(0);
  f.read(bytes.data(), std::streamsize(bytes.size()));
  if (!f) return absl::InternalError(absl::StrCat("cannot read ", path.string()));
  if (absl::Status s = MakeUuidDeterministic(bytes, path.string()); !s.ok()) return s;
  f.seekp(kUuidAt);
  f.write(bytes.data() + kUuidAt, kUuidLen);
  f.close();
  if (!f) return absl::InternalError(absl::StrCat("cannot rewrite the UUID of ", path.string()));
  return absl::OkStatus();
}

absl::Status MakeUuidDeterministic(std::string& bytes, const std::string& where) {
  if (bytes.size() < kUuidAt + kUuidLen || bytes.compare(0, 4, " BDV") != 0 ||
      bytes[kUuidAt + 8] != '-' || bytes[kUuidAt + 13] != '-') {
    return absl::InternalError(absl::StrCat(where, " has no OpenVDB header UUID"));
  }
  // Two FNV-1a-style 64-bit hashes of everything after the UUID, 8 bytes a step (then the
  // tail byte by byte), as a version-4-shaped UUID.
  uint64_t a = 0xcbf29ce484222325ull, b = 0x84222325cbf29ce4ull;
  size_t i = kUuidAt + kUuidLen;
  for (; i + 8 <= bytes.size(); i += 8) {
    uint64_t w;
    std::memcpy(&w, bytes.data() + i, 8);
    a = (a ^ w) * 0x100000001b3ull;
    b = (b ^ (w + 0x5b5b5b5b5b5b5b5bull)) * 0x100000001b3ull;
    a ^= a >> 29;
    b ^= b >> 31;
  }
  for (; i < bytes.size(); ++i) {
    const uint8_t c = uint8_t(bytes[i]);
    a = (a ^ c) * 0x100000001b3ull;
    b = (b ^ uint8_t(c + 0x5b)) * 0x100000001b3ull;
  }
  const std::string hex = absl::StrFormat("%016x%016x", a, b);
  const std::string uuid = absl::StrCat(hex.substr(0, 8), "-", hex.substr(8, 4), "-4",
                                        hex.substr(13, 3), "-a", hex.substr(17, 3), "-",
                                        hex.substr(20, 12));
  bytes.replace(kUuidAt, kUuidLen, uuid);
  return absl::OkStatus();
}

namespace {

/// Every grid of `path` (names null) or those named in `*names` that it has.
absl::StatusOr<VdbFileContents> ReadGrids(const std::filesystem::path& path, bool delay_load,
                                          const std::vector<std::string>* names) {
  EnsureOpenVdbInitialized();
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) {
    return absl::NotFoundError(absl::StrCat("no such OpenVDB file: ", path.string()));
  }
  try {
    openvdb::io::File file(path.string());
    file.open(delay_load);
    VdbFileContents out;
    if (names == nullptr) {
      out.grids = file.getGrids();
    } else {
      out.grids = std::make_shared<openvdb::GridPtrVec>();
      for (const std::string& name : *names) {
        if (file.hasGrid(name)) out.grids->push_back(file.readGrid(name));
      }
    }
    out.meta = file.getMetadata();
    file.close();
    if (!out.grids) out.grids = std::make_shared<openvdb::GridPtrVec>();
    if (!out.meta) out.meta = std::make_shared<openvdb::MetaMap>();
    return out;
  } catch (const std::exception& e) {
    return absl::DataLossError(
        absl::StrCat("cannot read OpenVDB file ", path.string(), ": ", e.what()));
  }
}

}  // namespace

absl::StatusOr<VdbFileContents> ReadVdbFile(const std::filesystem::path& path, bool delay_load) {
  return ReadGrids(path, delay_load, nullptr);
}

absl::StatusOr<VdbFileContents> ReadVdbGrids(const std::filesystem::path& path,
                                             const std::vector<std::string>& names) {
  return ReadGrids(path, false, &names);
}

openvdb::GridBase::Ptr FindGrid(const VdbFileContents& contents, const std::string& name) {
  for (const auto& g : *contents.grids) {
    if (g && g->getName() == name) return g;
  }
  return nullptr;
}

}  // namespace vasl::records::internal

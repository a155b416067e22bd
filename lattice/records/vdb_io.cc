#include "lattice/records/vdb_io.h"

#include <exception>
#include <mutex>
#include <system_error>

#include <openvdb/io/File.h>
#include <openvdb/points/PointDataGrid.h>

#include "absl/strings/str_cat.h"

namespace vasl::records::internal {

void EnsureOpenVdbInitialized() {
  static std::once_flag once;
  std::call_once(once, [] { openvdb::initialize(); });
}

absl::Status WriteVdbFile(const std::filesystem::path& path, const openvdb::GridCPtrVec& grids,
                          const openvdb::MetaMap& meta) {
  EnsureOpenVdbInitialized();
  try {
    openvdb::io::File file(path.string());
    uint32_t compression = openvdb::io::COMPRESS_ACTIVE_MASK;
    compression |= openvdb::io::Archive::hasBloscCompression() ? openvdb::io::COMPRESS_BLOSC
                                                               : openvdb::io::COMPRESS_ZIP;
    file.setCompression(compression);
    file.write(grids, meta);
    file.close();
  } catch (const std::exception& e) {
    return absl::InternalError(absl::StrCat("cannot write ", path.string(), ": ", e.what()));
  }
  return absl::OkStatus();
}

absl::StatusOr<VdbFileContents> ReadVdbFile(const std::filesystem::path& path, bool delay_load) {
  EnsureOpenVdbInitialized();
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) {
    return absl::NotFoundError(absl::StrCat("no such OpenVDB file: ", path.string()));
  }
  try {
    openvdb::io::File file(path.string());
    file.open(delay_load);
    VdbFileContents out;
    out.grids = file.getGrids();
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

openvdb::GridBase::Ptr FindGrid(const VdbFileContents& contents, const std::string& name) {
  for (const auto& g : *contents.grids) {
    if (g && g->getName() == name) return g;
  }
  return nullptr;
}

}  // namespace vasl::records::internal

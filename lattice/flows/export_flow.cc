// The export query (flows.h): a version as one merged OpenVDB file.
#include <system_error>

#include "absl/strings/str_cat.h"
#include "lattice/flows/flows.h"
#include "lattice/records/record_grid.h"

namespace vasl::flows {

absl::StatusOr<ExportResult> Export(const store::Snapshot& snapshot,
                                    const Eigen::Vector3d& origin_m,
                                    const std::filesystem::path& path) {
  if (absl::Status s = records::WriteVersionFile(snapshot.geometry, snapshot.records,
                                                 snapshot.fused, path, origin_m);
      !s.ok()) {
    return s;
  }
  ExportResult out;
  out.version = snapshot.version;
  out.vossel_count = int64_t(snapshot.geometry.size());
  out.record_count = int64_t(snapshot.records.size());
  std::error_code ec;
  out.size_bytes = int64_t(std::filesystem::file_size(path, ec));
  if (ec) return absl::InternalError(absl::StrCat("export: cannot stat ", path.string()));
  return out;
}

}  // namespace vasl::flows

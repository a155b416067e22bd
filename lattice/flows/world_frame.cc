// World and lattice coordinates (world_frame.h, VASL-MODEL §1).
#include "lattice/flows/world_frame.h"

#include <cmath>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "lattice/ingest/voxelise.h"

namespace vasl::flows {

double LatticeReachM(double vossel_size_m) { return ingest::kMaxVosselIndex * vossel_size_m; }

Eigen::Vector3d OriginOfFirstScan(const ingest::ScanInput& scan) {
  const Eigen::Vector3d o = scan.pose.o_world;
  return {1000.0 * std::round(o.x() / 1000.0), 1000.0 * std::round(o.y() / 1000.0),
          1000.0 * std::round(o.z() / 1000.0)};
}

geometry::Pose Shifted(geometry::Pose pose, const Eigen::Vector3d& by) {
  pose.o_world += by;
  return pose;
}

void ShiftScan(store::ScanInfo& scan, const Eigen::Vector3d& by) {
  scan.pose = Shifted(scan.pose, by);
  for (store::SourceInfo& src : scan.sources) src.pose = Shifted(src.pose, by);
  for (store::VisualReferenceInfo& ref : scan.visual_references) ref.pose = Shifted(ref.pose, by);
}

absl::Status CheckWithinReach(const Eigen::Vector3d& world_m, const Eigen::Vector3d& origin,
                              double vossel_size_m, const std::string& what) {
  const double reach = LatticeReachM(vossel_size_m);
  if ((world_m - origin).cwiseAbs().maxCoeff() <= reach) return absl::OkStatus();
  return absl::InvalidArgumentError(absl::StrFormat(
      "%s at (%.3f, %.3f, %.3f) m lies beyond the lattice: a project with %g m vossels holds "
      "positions within ±%.0f m of its origin (%.3f, %.3f, %.3f) on each axis; put the site in a "
      "project whose origin is near it (vasl project create --origin X,Y,Z)",
      what, world_m.x(), world_m.y(), world_m.z(), vossel_size_m, reach, origin.x(), origin.y(),
      origin.z()));
}

absl::Status CheckScanWithinReach(const ingest::ScanInput& scan, const Eigen::Vector3d& origin,
                                  double vossel_size_m) {
  if (absl::Status s = CheckWithinReach(scan.pose.o_world, origin, vossel_size_m,
                                        absl::StrCat("scan '", scan.scan_name, "'"));
      !s.ok()) {
    return s;
  }
  for (const ingest::PanoramaData& pano : scan.panoramas) {
    if (absl::Status s = CheckWithinReach(
            pano.pose.o_world, origin, vossel_size_m,
            absl::StrCat("image '", pano.name, "' of scan '", scan.scan_name, "'"));
        !s.ok()) {
      return s;
    }
  }
  return absl::OkStatus();
}

}  // namespace vasl::flows

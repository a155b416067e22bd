#include "lattice/geometry/pose.h"

#include <cmath>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"

namespace vasl::geometry {

absl::StatusOr<Pose> MakePose(const Eigen::Vector3d& position_m, const Eigen::Vector4d& quat_xyzw) {
  if (!position_m.allFinite()) {
    return absl::InvalidArgumentError(
        absl::StrCat("pose position must be finite metres, got (", position_m.x(), ", ",
                     position_m.y(), ", ", position_m.z(), ")"));
  }
  if (!quat_xyzw.allFinite()) {
    return absl::InvalidArgumentError("pose quaternion (x, y, z, w) must be finite");
  }
  const double norm = quat_xyzw.norm();
  if (norm < 1e-9) {
    return absl::InvalidArgumentError("pose quaternion (x, y, z, w) must not be zero");
  }
  Pose pose;
  pose.q_world_sensor =
      Eigen::Quaterniond(quat_xyzw[3], quat_xyzw[0], quat_xyzw[1], quat_xyzw[2]).normalized();
  pose.o_world = position_m;
  return pose;
}

}  // namespace vasl::geometry

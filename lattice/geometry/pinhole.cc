#include "lattice/geometry/pinhole.h"

#include <algorithm>
#include <cmath>

#include "absl/strings/str_cat.h"

namespace vasl::geometry {

absl::Status ValidatePinhole(const PinholeIntrinsics& k) {
  for (double v : {k.fx_px, k.fy_px, k.cx_px, k.cy_px, k.k1, k.k2, k.k3, k.p1, k.p2}) {
    if (!std::isfinite(v)) return absl::InvalidArgumentError("pinhole intrinsics must be finite");
  }
  if (!(k.fx_px > 0.0 && k.fy_px > 0.0)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "pinhole focal lengths must be > 0 pixels, got fx ", k.fx_px, ", fy ", k.fy_px));
  }
  if (std::max({std::abs(k.k1), std::abs(k.k2), std::abs(k.k3)}) > 10.0 ||
      std::max(std::abs(k.p1), std::abs(k.p2)) > 1.0) {
    return absl::InvalidArgumentError(
        "pinhole distortion out of range (|k1|, |k2|, |k3| <= 10, |p1|, |p2| <= 1)");
  }
  return absl::OkStatus();
}
namespace {

// Brown–Conrady: normalised undistorted (x, y) to normalised distorted coordinates.
Eigen::Vector2d Distort(const Eigen::Vector2d& xy, const PinholeIntrinsics& k) {
  const double x = xy.x(), y = xy.y();
  const double r2 = x * x + y * y;
  const double radial = 1.0 + r2 * (k.k1 + r2 * (k.k2 + r2 * k.k3));
  return {x * radial + 2.0 * k.p1 * x * y + k.p2 * (r2 + 2.0 * x * x),
          y * radial + k.p1 * (r2 + 2.0 * y * y) + 2.0 * k.p2 * x * y};
}

}  // namespace

std::optional<Eigen::Vector2d> PinholeProject(const Eigen::Vector3d& p_cam,
                                              const PinholeIntrinsics& k) {
  if (!(p_cam.z() > 0.0)) return std::nullopt;
  const Eigen::Vector2d xd = Distort({p_cam.x() / p_cam.z(), p_cam.y() / p_cam.z()}, k);
  return Eigen::Vector2d(k.fx_px * xd.x() + k.cx_px, k.fy_px * xd.y() + k.cy_px);
}

Eigen::Vector3d PinholeUnproject(const Eigen::Vector2d& uv_px, const PinholeIntrinsics& k) {
  const Eigen::Vector2d xd((uv_px.x() - k.cx_px) / k.fx_px, (uv_px.y() - k.cy_px) / k.fy_px);
  Eigen::Vector2d x = xd;
  for (int it = 0; it < 50; ++it) {  // x ← x + (xd − D(x)): contraction for mild distortion
    const Eigen::Vector2d step = xd - Distort(x, k);
    x += step;
    if (step.squaredNorm() < 1e-30) break;
  }
  return Eigen::Vector3d(x.x(), x.y(), 1.0).normalized();
}

}  // namespace vasl::geometry

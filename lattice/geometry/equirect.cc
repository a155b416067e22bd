#include "lattice/geometry/equirect.h"

#include <algorithm>

namespace vasl::geometry {

Eigen::Vector2d EquirectAngles(const Eigen::Vector3d& d_sensor) {
  const Eigen::Vector3d d = d_sensor.normalized();
  const double phi = std::atan2(d.y(), d.x());
  const double psi = std::asin(std::clamp(d.z(), -1.0, 1.0));
  return {phi, psi};
}

Eigen::Vector2d EquirectProject(const Eigen::Vector3d& d_sensor, const EquirectSize& size) {
  const Eigen::Vector2d a = EquirectAngles(d_sensor);
  double u = size.width_px * (0.5 - a[0] / (2.0 * M_PI));
  const double v = size.height_px * (0.5 - a[1] / M_PI);
  if (u >= size.width_px) u -= size.width_px;  // φ = −π maps to u = W, the seam: wrap to 0.
  if (u < 0.0) u += size.width_px;
  return {u, v};
}

Eigen::Vector3d EquirectUnproject(double u_px, double v_px, const EquirectSize& size) {
  const double phi = EquirectAzimuthRad(u_px, size);
  const double psi = EquirectElevationRad(v_px, size);
  return EquirectDirection(std::cos(phi), std::sin(phi), std::cos(psi), std::sin(psi));
}

double EquirectPixelAngleRad(double elevation_rad, const EquirectSize& size) {
  return std::max(ElevationPitchRad(size), std::cos(elevation_rad) * AzimuthPitchRad(size));
}

}  // namespace vasl::geometry

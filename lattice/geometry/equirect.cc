#include "lattice/geometry/equirect.h"

#include <algorithm>
#include <cmath>

namespace vasl::geometry {

Eigen::Vector3d EquirectUnproject(double u_px, double v_px, const EquirectSize& size) {
  const double phi = EquirectAzimuthRad(u_px, size);
  const double psi = EquirectElevationRad(v_px, size);
  return EquirectDirection(std::cos(phi), std::sin(phi), std::cos(psi), std::sin(psi));
}

double EquirectPixelAngleRad(double elevation_rad, const EquirectSize& size) {
  return std::max(ElevationPitchRad(size), std::cos(elevation_rad) * AzimuthPitchRad(size));
}

}  // namespace vasl::geometry

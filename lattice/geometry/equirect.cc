#include "lattice/geometry/equirect.h"

#include <algorithm>
#include <cmath>

namespace vasl::geometry {

double Atan2(double y, double x) {
  // atan of |y/x| or |x/y| (whichever is ≤ 1, t below), Cephes' rational approximation on
  // [0, 0.66] after the reduction t → (t − 1)/(t + 1) above 0.66 (relative error ~1e-16 before
  // the reduction's rounding), then the quadrant. No rounding-mode save and restore, which
  // the C library's atan2 pays on every call.
  constexpr double kPio2 = 1.57079632679489661923, kPio4 = 0.78539816339744830962;
  constexpr double kMoreBits = 6.123233995736765886130e-17;  // π/2 − kPio2
  if (!(std::isfinite(x) && std::isfinite(y))) return std::atan2(y, x);
  const double ax = std::fabs(x), ay = std::fabs(y);
  if (ax == 0.0 && ay == 0.0) return std::atan2(y, x);  // signed zeros: as the C library
  const bool swap = ay > ax;  // atan(y/x) = π/2 − atan(x/y)
  double t = swap ? ax / ay : ay / ax;
  double base = 0.0, more = 0.0;
  if (t > 0.66) {
    base = kPio4;
    more = 0.5 * kMoreBits;
    t = (t - 1.0) / (t + 1.0);
  }
  const double z = t * t;
  const double p =
      (((-8.750608600031904122785e-1 * z - 1.615753718733365076637e1) * z -
        7.500855792314704667340e1) * z - 1.228866684490136173410e2) * z -
      6.485021904942025371773e1;
  const double q =
      ((((z + 2.485846490142306297962e1) * z + 1.650270098316988542046e2) * z +
        4.328810604912902668951e2) * z + 4.853903996359136964868e2) * z +
      1.945506571482613964425e2;
  double a = base + (t * (z * p / q) + t + more);  // atan(t) in [0, π/4]
  if (swap) a = (kPio2 - a) + kMoreBits;
  if (x < 0.0) a = (kPio2 - a) + kPio2 + 2.0 * kMoreBits;  // π − a
  return y < 0.0 || (y == 0.0 && std::signbit(y)) ? -a : a;
}

Eigen::Vector2d EquirectAngles(const Eigen::Vector3d& d_sensor) {
  // atan2 of the coordinates, which needs no normalising; the elevation as the angle above
  // the horizontal plane, atan2(z, |xy|), equal to asin(z/|d|).
  const double phi = Atan2(d_sensor.y(), d_sensor.x());
  const double psi = Atan2(d_sensor.z(), std::sqrt(d_sensor.x() * d_sensor.x() +
                                                   d_sensor.y() * d_sensor.y()));
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

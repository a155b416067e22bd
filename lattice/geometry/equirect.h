/// @file equirect.h
/// @brief The equirectangular projection π_eqr of 360° panoramas (VASL-MODEL §2.1).
/// @details Continuous pixel coordinates: pixel (i, j) spans [i, i+1) × [j, j+1) and has its
///          centre at (i + 0.5, j + 0.5). Column 0 starts at azimuth +π (sensor −x), azimuth 0
///          (sensor +x) is the image centre column, azimuth increases toward +y going left;
///          row 0 looks up (+z). Columns wrap at the seam.
#pragma once

#include <cmath>
#include <cstdint>

#include <Eigen/Core>

namespace vasl::geometry {

/// Size of an equirectangular raster, pixels.
struct EquirectSize {
  int width_px = 0;   ///< W: columns, spanning 2π of azimuth.
  int height_px = 0;  ///< H: rows, spanning π of elevation.
};

/// §2.1 forward: sensor-frame direction (need not be unit, must be non-zero) to continuous
/// pixel coordinates (u, v) with u in [0, W) and v in [0, H].
inline Eigen::Vector2d EquirectProject(const Eigen::Vector3d& d_sensor, const EquirectSize& size);

/// §2.1 inverse: continuous pixel coordinates to a unit sensor-frame direction.
Eigen::Vector3d EquirectUnproject(double u_px, double v_px, const EquirectSize& size);

/// §2.1: the azimuth φ of continuous column u and the elevation ψ of continuous row v, radians.
inline double EquirectAzimuthRad(double u_px, const EquirectSize& size) {
  return 2.0 * M_PI * (0.5 - u_px / size.width_px);
}
inline double EquirectElevationRad(double v_px, const EquirectSize& size) {
  return M_PI * (0.5 - v_px / size.height_px);
}
/// §2.1 inverse from the angles' cosines and sines: (cos ψ cos φ, cos ψ sin φ, sin ψ), the unit
/// direction EquirectUnproject gives (for a caller that computes them once per column and row).
inline Eigen::Vector3d EquirectDirection(double cos_phi, double sin_phi, double cos_psi,
                                         double sin_psi) {
  return {cos_psi * cos_phi, cos_psi * sin_phi, sin_psi};
}

/// atan(t) − t for t in [0, 0.66] by Cephes' rational approximation, into `out`: the
/// polynomial both Atan2 and Atan2Lanes take (T a double or a GCC vector of doubles, which by
/// value would change the ABI under the baseline instruction set).
template <typename T>
[[gnu::always_inline]] inline void AtanLessT(const T& t, T& out) {
  const T z = t * t;
  const T p =
      (((-8.750608600031904122785e-1 * z - 1.615753718733365076637e1) * z -
        7.500855792314704667340e1) * z - 1.228866684490136173410e2) * z -
      6.485021904942025371773e1;
  const T q =
      ((((z + 2.485846490142306297962e1) * z + 1.650270098316988542046e2) * z +
        4.328810604912902668951e2) * z + 4.853903996359136964868e2) * z +
      1.945506571482613964425e2;
  out = t * (z * p / q);
}

/// Atan2's constants: π/2 and π/4 rounded, and π/2 − kAtanPio2.
inline constexpr double kAtanPio2 = 1.57079632679489661923, kAtanPio4 = 0.78539816339744830962;
inline constexpr double kAtanMoreBits = 6.123233995736765886130e-17;

/// atan2(y, x) in [−π, π], as the C library's to within 2 ulp of π (8.9e-16 rad; 4.4e-16
/// measured), signed zeros included, without its rounding-mode guard: the angles of every
/// sample a visibility test or a splat projects.
inline double Atan2(double y, double x) {
  // atan of |y/x| or |x/y| (whichever is ≤ 1, t below), Cephes' rational approximation on
  // [0, 0.66] after the reduction t → (t − 1)/(t + 1) above 0.66 (relative error ~1e-16 before
  // the reduction's rounding), then the quadrant. No rounding-mode save and restore, which
  // the C library's atan2 pays on every call.
  if (!(std::isfinite(x) && std::isfinite(y))) return std::atan2(y, x);
  const double ax = std::fabs(x), ay = std::fabs(y);
  if (ax == 0.0 && ay == 0.0) return std::atan2(y, x);  // signed zeros: as the C library
  const bool swap = ay > ax;  // atan(y/x) = π/2 − atan(x/y)
  double t = swap ? ax / ay : ay / ax;
  double base = 0.0, more = 0.0;
  if (t > 0.66) {
    base = kAtanPio4;
    more = 0.5 * kAtanMoreBits;
    t = (t - 1.0) / (t + 1.0);
  }
  double atan_less_t;
  AtanLessT(t, atan_less_t);
  double a = base + (atan_less_t + t + more);  // atan(t) in [0, π/4]
  if (swap) a = (kAtanPio2 - a) + kAtanMoreBits;
  if (x < 0.0) a = (kAtanPio2 - a) + kAtanPio2 + 2.0 * kAtanMoreBits;  // π − a
  return y < 0.0 || (y == 0.0 && std::signbit(y)) ? -a : a;
}

/// Atan2 of the lanes of GCC vectors of doubles V (I: their 64-bit integer lanes, a compare's
/// mask) into `out`, for finite (y, x) not both zero: Atan2's operations in its order, its
/// branches as selects, so that each lane is Atan2's result bit for bit (the build does not
/// fuse a·b + c). By reference: a vector returned by value would change the ABI under the
/// baseline instruction set.
template <typename V, typename I>
[[gnu::always_inline]] inline void Atan2Lanes(const V& y, const V& x, V& out) {
  constexpr int64_t kMagnitude = 0x7fffffffffffffffLL;
  const V ax = (V)((I)x & kMagnitude), ay = (V)((I)y & kMagnitude);
  const I swap = ay > ax;
  V t = (swap ? ax : ay) / (swap ? ay : ax);
  const I big = t > 0.66;
  t = big ? (t - 1.0) / (t + 1.0) : t;
  const V zero = {};
  const V base = big ? zero + kAtanPio4 : zero;
  const V more = big ? zero + 0.5 * kAtanMoreBits : zero;
  V atan_less_t;
  AtanLessT(t, atan_less_t);
  V a = base + (atan_less_t + t + more);
  a = swap ? (kAtanPio2 - a) + kAtanMoreBits : a;
  a = x < 0.0 ? (kAtanPio2 - a) + kAtanPio2 + 2.0 * kAtanMoreBits : a;
  out = (y < 0.0) | ((y == 0.0) & ((I)y < 0)) ? -a : a;
}

/// Azimuth φ and elevation ψ (radians) of a sensor-frame direction (§2.1), of any length.
inline Eigen::Vector2d EquirectAngles(const Eigen::Vector3d& d_sensor) {
  // atan2 of the coordinates, which needs no normalising; the elevation as the angle above
  // the horizontal plane, atan2(z, |xy|), equal to asin(z/|d|).
  const double phi = Atan2(d_sensor.y(), d_sensor.x());
  const double psi = Atan2(d_sensor.z(), std::sqrt(d_sensor.x() * d_sensor.x() +
                                                   d_sensor.y() * d_sensor.y()));
  return {phi, psi};
}

/// Wraps a column index into [0, W) across the seam (§2.1).
inline int WrapColumn(int i, int width_px) {
  const int m = i % width_px;
  return m < 0 ? m + width_px : m;
}

/// Angular pitch of one pixel: Δφ = 2π/W (azimuth), Δψ = π/H (elevation), radians.
inline double AzimuthPitchRad(const EquirectSize& s) { return 2.0 * M_PI / s.width_px; }
inline double ElevationPitchRad(const EquirectSize& s) { return M_PI / s.height_px; }

/// §3: the angular sampling of one equirect pixel at elevation ψ,
/// θ_pix = max(Δψ, cosψ·Δφ), radians.
double EquirectPixelAngleRad(double elevation_rad, const EquirectSize& size);

// Defined here, after Atan2 and EquirectAngles, so that the loops projecting every sample
// inline it.
inline Eigen::Vector2d EquirectProject(const Eigen::Vector3d& d_sensor, const EquirectSize& size) {
  const Eigen::Vector2d a = EquirectAngles(d_sensor);
  double u = size.width_px * (0.5 - a[0] / (2.0 * M_PI));
  const double v = size.height_px * (0.5 - a[1] / M_PI);
  if (u >= size.width_px) u -= size.width_px;  // φ = −π maps to u = W, the seam: wrap to 0.
  if (u < 0.0) u += size.width_px;
  return {u, v};
}

}  // namespace vasl::geometry

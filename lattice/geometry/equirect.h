/// @file equirect.h
/// @brief The equirectangular projection π_eqr of 360° panoramas (VASL-MODEL §2.1).
/// @details Continuous pixel coordinates: pixel (i, j) spans [i, i+1) × [j, j+1) and has its
///          centre at (i + 0.5, j + 0.5). Column 0 starts at azimuth +π (sensor −x), azimuth 0
///          (sensor +x) is the image centre column, azimuth increases toward +y going left;
///          row 0 looks up (+z). Columns wrap at the seam.
#pragma once

#include <cmath>

#include <Eigen/Core>

namespace vasl::geometry {

/// Size of an equirectangular raster, pixels.
struct EquirectSize {
  int width_px = 0;   ///< W: columns, spanning 2π of azimuth.
  int height_px = 0;  ///< H: rows, spanning π of elevation.
};

/// §2.1 forward: sensor-frame direction (need not be unit, must be non-zero) to continuous
/// pixel coordinates (u, v) with u in [0, W) and v in [0, H].
Eigen::Vector2d EquirectProject(const Eigen::Vector3d& d_sensor, const EquirectSize& size);

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

/// atan2(y, x) in [−π, π], as the C library's to within 2 ulp of π (8.9e-16 rad; 4.4e-16
/// measured), signed zeros included, without its rounding-mode guard: the angles of every
/// sample a visibility test or a splat projects.
double Atan2(double y, double x);

/// Azimuth φ and elevation ψ (radians) of a sensor-frame direction (§2.1), of any length.
Eigen::Vector2d EquirectAngles(const Eigen::Vector3d& d_sensor);

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

}  // namespace vasl::geometry

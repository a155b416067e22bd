/// @file pinhole.h
/// @brief Pinhole cameras with Brown–Conrady distortion (VASL-MODEL §2.2).
/// @details Camera frame: x right, y down, z forward. Pixel (i, j) has its centre at
///          (i + 0.5, j + 0.5) when cx, cy follow that convention.
#pragma once

#include <optional>

#include <Eigen/Core>

#include "absl/status/status.h"

namespace vasl::geometry {

/// Intrinsics of a pinhole camera, pixels; distortion coefficients are unitless.
struct PinholeIntrinsics {
  int width_px = 0;    ///< image columns
  int height_px = 0;   ///< image rows
  double fx_px = 0.0;  ///< focal length along x, pixels
  double fy_px = 0.0;  ///< focal length along y, pixels
  double cx_px = 0.0;  ///< principal point x, pixels
  double cy_px = 0.0;  ///< principal point y, pixels
  double k1 = 0.0, k2 = 0.0, k3 = 0.0;  ///< radial distortion
  double p1 = 0.0, p2 = 0.0;            ///< tangential distortion
};

/// INVALID_ARGUMENT unless the intrinsics are finite, the focal lengths positive and the
/// distortion moderate (|k1|, |k2|, |k3| ≤ 10, |p1|, |p2| ≤ 1): what renders and
/// back-projection accept. The image size is not checked (callers take it from elsewhere).
absl::Status ValidatePinhole(const PinholeIntrinsics& k);

/// §2.2 forward: camera-frame point to continuous pixel coordinates; nullopt behind the camera
/// (Z ≤ 0). The pixel may fall outside the image; callers test the bounds.
std::optional<Eigen::Vector2d> PinholeProject(const Eigen::Vector3d& p_cam,
                                              const PinholeIntrinsics& k);

/// §2.2 inverse: continuous pixel coordinates to a unit camera-frame ray, undistorted by
/// fixed-point iteration (converges for the moderate distortion of survey cameras).
Eigen::Vector3d PinholeUnproject(const Eigen::Vector2d& uv_px, const PinholeIntrinsics& k);

/// §3: angular sampling of one pinhole pixel, θ_pix = pixel_pitch / focal_length, radians.
inline double PinholePixelAngleRad(const PinholeIntrinsics& k) {
  return 1.0 / (0.5 * (k.fx_px + k.fy_px));
}

}  // namespace vasl::geometry

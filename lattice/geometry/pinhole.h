/// @file pinhole.h
/// @brief Pinhole cameras with Brown–Conrady distortion (VASL-MODEL §2.2), and fisheye lenses
///        in the same camera frame.
/// @details Camera frame: x right, y down, z forward. Pixel (i, j) has its centre at
///          (i + 0.5, j + 0.5) when cx, cy follow that convention. A fisheye lens *(choice: an
///          extension of §2.2, which models perspective lenses alone)* is Kannala–Brandt's
///          equidistant model as OpenCV's cv::fisheye and ROS's "equidistant" camera_info
///          calibrate it: a direction at angle θ from the optical axis and azimuth (x, y)/r
///          about it lands at distorted radius θ_d = θ(1 + k1θ² + k2θ⁴ + k3θ⁶ + k4θ⁸), pixel
///          (fx·θ_d·x/r + cx, fy·θ_d·y/r + cy). It sees beyond 90° (θ up to π), as far as θ_d
///          grows with θ (FisheyeMaxAngleRad): beyond that the polynomial folds back and
///          would put a direction behind the lens on the image, so nothing projects there.
#pragma once

#include <optional>

#include <Eigen/Core>

#include "absl/status/status.h"

namespace vasl::geometry {

/// The lens model of a camera in the pinhole camera frame.
enum class Lens {
  kBrownConrady,  ///< §2.2: perspective, radial k1-k3 and tangential p1, p2
  kFisheye,       ///< Kannala–Brandt equidistant: θ_d = θ(1 + k1θ² + k2θ⁴ + k3θ⁶ + k4θ⁸)
};

/// Intrinsics of a pinhole camera, pixels; distortion coefficients are unitless.
struct PinholeIntrinsics {
  int width_px = 0;    ///< image columns
  int height_px = 0;   ///< image rows
  double fx_px = 0.0;  ///< focal length along x, pixels
  double fy_px = 0.0;  ///< focal length along y, pixels
  double cx_px = 0.0;  ///< principal point x, pixels
  double cy_px = 0.0;  ///< principal point y, pixels
  double k1 = 0.0, k2 = 0.0, k3 = 0.0;  ///< radial distortion
  double p1 = 0.0, p2 = 0.0;            ///< tangential distortion (Brown–Conrady only)
  Lens lens = Lens::kBrownConrady;
  double k4 = 0.0;                      ///< fisheye only: θ⁹'s coefficient
  /// Fisheye only: the lens's field of view, radians across (a circular fisheye's image
  /// circle, 2θ_max); 0: as far as θ_d grows. Nothing beyond half of it projects.
  double field_of_view_rad = 0.0;
};

/// INVALID_ARGUMENT unless the intrinsics are finite, the focal lengths positive and the
/// distortion moderate (|k1|, |k2|, |k3|, |k4| ≤ 10, |p1|, |p2| ≤ 1), with k4 = 0 and no field
/// of view for a Brown–Conrady lens, p1 = p2 = 0 for a fisheye (whose θ_d, with such k, grows
/// at least to 10° from its axis) and its field of view, if any, in (0, 2π]: what ingest,
/// renders and back-projection accept. The image size is not checked (callers take it from
/// elsewhere).
absl::Status ValidatePinhole(const PinholeIntrinsics& k);

/// A fisheye's widest angle from the optical axis (radians, at most π) that it sees: up to
/// where θ_d stops growing with θ, and within half its field of view when it gives one; π for
/// a Brown–Conrady lens (whose own limit is z > 0).
double FisheyeMaxAngleRad(const PinholeIntrinsics& k);

/// Whether continuous pixel coordinates lie where the lens sees: within the radius of
/// FisheyeMaxAngleRad for a fisheye (a circular fisheye's image circle); always for a
/// Brown–Conrady lens (the image's bounds are the caller's).
bool PinholeSees(const Eigen::Vector2d& uv_px, const PinholeIntrinsics& k);

/// §2.2 forward: camera-frame point to continuous pixel coordinates; nullopt behind the camera
/// (Z ≤ 0; a fisheye: beyond FisheyeMaxAngleRad). The pixel may fall outside the image;
/// callers test the bounds.
std::optional<Eigen::Vector2d> PinholeProject(const Eigen::Vector3d& p_cam,
                                              const PinholeIntrinsics& k);

/// §2.2 inverse: continuous pixel coordinates to a unit camera-frame ray, undistorted by
/// fixed-point iteration (converges for the moderate distortion of survey cameras); a
/// fisheye's θ solved from θ_d by safeguarded Newton steps, and held at FisheyeMaxAngleRad for
/// a pixel beyond it (outside the lens's image circle).
Eigen::Vector3d PinholeUnproject(const Eigen::Vector2d& uv_px, const PinholeIntrinsics& k);

/// §3: angular sampling of one pinhole pixel, θ_pix = pixel_pitch / focal_length, radians (a
/// fisheye's on its axis, where dθ_d/dθ = 1).
inline double PinholePixelAngleRad(const PinholeIntrinsics& k) {
  return 1.0 / (0.5 * (k.fx_px + k.fy_px));
}

/// The widest θ_pix PinholePixelAngleRad(k, d_cam) gives: a fisheye's pixels near its fold.
constexpr double kMaxPinholePixelAngleRad = 0.1;

/// §3's θ_pix of the pixel that direction `d_cam` (camera frame) falls in. A Brown–Conrady
/// lens: pixel pitch over focal length, as §3 writes it, whatever the direction. A fisheye
/// *(choice: §3's rule for an equirect panorama, the larger of a pixel's two angular pitches,
/// carried over to the lens that, like a panorama, sees far from its axis)*: at angle θ from
/// the axis a pixel spans 1/(f·dθ_d/dθ) radially and sin θ/(f·θ_d) across (f the mean focal
/// length), and θ_pix is the larger: 1/f on the axis, more where θ_d grows slower than θ
/// (k1 < 0), without bound near the lens's fold, so held at kMaxPinholePixelAngleRad.
double PinholePixelAngleRad(const PinholeIntrinsics& k, const Eigen::Vector3d& d_cam);

}  // namespace vasl::geometry

/// @file image_projection.h
/// @brief Where a camera's image sees (§2.1 equirect, §2.2 pinhole) and how finely (§3): one
///        implementation for the ingest samplers and visibility, calibration and the render's
///        colour detail.
#pragma once

#include <optional>

#include <Eigen/Core>

#include "lattice/geometry/equirect.h"
#include "lattice/geometry/pinhole.h"

namespace vasl::geometry {

/// Where a camera's image sees (§2.1 equirect, §2.2 pinhole) and how finely (§3), for an image
/// of the given size.
class ImageProjection {
 public:
  ImageProjection() = default;  ///< an empty panorama (0 × 0)
  /// `pinhole` set: a pinhole image (its width and height are taken from here); unset: an
  /// equirectangular one. `angular_resolution_rad` > 0 overrides θ_pix (§3).
  ImageProjection(std::optional<PinholeIntrinsics> pinhole, int width_px, int height_px,
                  double angular_resolution_rad = 0.0);
  /// True for a panorama (columns wrap across the seam), false for a pinhole image.
  bool panorama() const { return !pinhole_; }
  /// Continuous pixel coordinates of a camera-frame direction; nullopt behind a pinhole camera.
  std::optional<Eigen::Vector2d> Project(const Eigen::Vector3d& d_cam) const;
  /// §2.1/§2.2 inverse: the unit camera-frame ray through continuous pixel coordinates.
  Eigen::Vector3d Unproject(const Eigen::Vector2d& uv_px) const;
  /// True when pixel coordinates lie on the image (always for a panorama).
  bool Inside(const Eigen::Vector2d& uv_px) const;
  /// §3 θ_pix in direction `d_cam`: the camera's own angular resolution when it gives one,
  /// else max(Δψ, cosψ·Δφ) (equirect) or PinholePixelAngleRad(k, d_cam) (pixel pitch over
  /// focal length; a fisheye's grows away from its axis).
  double PixelAngleRad(const Eigen::Vector3d& d_cam) const;
  /// θ_pix on the equator (equirect) or on the optical axis (pinhole, fisheye): what a
  /// depth panorama's splats of the camera grow by (§5), one value for the whole source.
  double AxisPixelAngleRad() const;
  /// The pitch of the camera's depth panorama (its Δ in the visibility tolerance): its angular
  /// resolution, Δψ, or the pinhole pixel angle.
  double PitchRad() const;
  /// Largest angle between the optical axis (+z) and a ray of the image's border; π for a
  /// panorama.
  double HalfFieldRad() const;

 private:
  std::optional<PinholeIntrinsics> pinhole_;
  EquirectSize size_;
  double angular_resolution_rad_ = 0.0;
};

}  // namespace vasl::geometry

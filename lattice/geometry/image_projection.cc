#include "lattice/geometry/image_projection.h"

#include <algorithm>
#include <cmath>
#include <utility>

namespace vasl::geometry {

ImageProjection::ImageProjection(std::optional<PinholeIntrinsics> pinhole, int width_px,
                                 int height_px, double angular_resolution_rad)
    : pinhole_(std::move(pinhole)), size_{width_px, height_px},
      angular_resolution_rad_(angular_resolution_rad) {
  if (pinhole_) {
    pinhole_->width_px = width_px;
    pinhole_->height_px = height_px;
  }
}

std::optional<Eigen::Vector2d> ImageProjection::Project(const Eigen::Vector3d& d_cam) const {
  if (!pinhole_) return EquirectProject(d_cam, size_);  // §2.1
  return PinholeProject(d_cam, *pinhole_);              // §2.2
}

Eigen::Vector3d ImageProjection::Unproject(const Eigen::Vector2d& uv) const {
  if (!pinhole_) return EquirectUnproject(uv.x(), uv.y(), size_);  // §2.1
  return PinholeUnproject(uv, *pinhole_);                         // §2.2
}

bool ImageProjection::Inside(const Eigen::Vector2d& uv) const {
  if (!pinhole_) return true;
  return uv.x() >= 0.0 && uv.x() <= size_.width_px && uv.y() >= 0.0 && uv.y() <= size_.height_px;
}

double ImageProjection::PixelAngleRad(const Eigen::Vector3d& d_cam) const {
  if (angular_resolution_rad_ > 0.0) return angular_resolution_rad_;
  if (pinhole_) return PinholePixelAngleRad(*pinhole_, d_cam);  // §3: pitch over focal length
  const double psi = std::asin(std::clamp(d_cam.z() / d_cam.norm(), -1.0, 1.0));
  return EquirectPixelAngleRad(psi, size_);  // §3
}

double ImageProjection::AxisPixelAngleRad() const {
  if (angular_resolution_rad_ > 0.0) return angular_resolution_rad_;
  if (pinhole_) return PinholePixelAngleRad(*pinhole_);
  return EquirectPixelAngleRad(0.0, size_);
}

double ImageProjection::PitchRad() const {
  if (angular_resolution_rad_ > 0.0) return angular_resolution_rad_;
  if (pinhole_) return PinholePixelAngleRad(*pinhole_);
  return ElevationPitchRad(size_);
}

double ImageProjection::HalfFieldRad() const {
  if (!pinhole_) return M_PI;
  double widest = 0.0;
  const double W = size_.width_px, H = size_.height_px;
  for (const Eigen::Vector2d& corner : {Eigen::Vector2d(0, 0), Eigen::Vector2d(W, 0),
                                        Eigen::Vector2d(0, H), Eigen::Vector2d(W, H),
                                        Eigen::Vector2d(W / 2, 0), Eigen::Vector2d(W / 2, H),
                                        Eigen::Vector2d(0, H / 2), Eigen::Vector2d(W, H / 2)}) {
    const Eigen::Vector3d d = PinholeUnproject(corner, *pinhole_);
    widest = std::max(widest, std::acos(std::clamp(d.z() / d.norm(), -1.0, 1.0)));
  }
  return widest;
}

}  // namespace vasl::geometry

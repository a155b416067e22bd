#include "lattice/geometry/pinhole.h"

#include <algorithm>
#include <cmath>

#include "absl/strings/str_cat.h"

namespace vasl::geometry {

absl::Status ValidatePinhole(const PinholeIntrinsics& k) {
  for (double v : {k.fx_px, k.fy_px, k.cx_px, k.cy_px, k.k1, k.k2, k.k3, k.p1, k.p2, k.k4,
                   k.field_of_view_rad}) {
    if (!std::isfinite(v)) return absl::InvalidArgumentError("pinhole intrinsics must be finite");
  }
  if (!(k.fx_px > 0.0 && k.fy_px > 0.0)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "pinhole focal lengths must be > 0 pixels, got fx ", k.fx_px, ", fy ", k.fy_px));
  }
  if (std::max({std::abs(k.k1), std::abs(k.k2), std::abs(k.k3), std::abs(k.k4)}) > 10.0 ||
      std::max(std::abs(k.p1), std::abs(k.p2)) > 1.0) {
    return absl::InvalidArgumentError(
        "pinhole distortion out of range (|k1|, |k2|, |k3|, |k4| <= 10, |p1|, |p2| <= 1)");
  }
  if (k.lens == Lens::kBrownConrady && (k.k4 != 0.0 || k.field_of_view_rad != 0.0)) {
    return absl::InvalidArgumentError("k4 and a field of view are a fisheye lens's: a "
                                      "Brown-Conrady lens has k1-k3, p1, p2");
  }
  if (!(k.field_of_view_rad >= 0.0 && k.field_of_view_rad <= 2.0 * M_PI)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "a fisheye's field of view lies in (0, 360] degrees (0: unlimited), got ",
        k.field_of_view_rad * 180.0 / M_PI));
  }
  if (k.lens == Lens::kFisheye) {
    if (k.p1 != 0.0 || k.p2 != 0.0) {
      return absl::InvalidArgumentError("a fisheye lens (Kannala-Brandt) has k1-k4 and no "
                                        "tangential p1, p2");
    }
  }
  return absl::OkStatus();
}

namespace {

// Kannala–Brandt: θ_d(θ) and its derivative.
double FisheyeRadius(double theta, const PinholeIntrinsics& k) {
  const double t2 = theta * theta;
  return theta * (1.0 + t2 * (k.k1 + t2 * (k.k2 + t2 * (k.k3 + t2 * k.k4))));
}
double FisheyeSlope(double theta, const PinholeIntrinsics& k) {
  const double t2 = theta * theta;
  return 1.0 + t2 * (3.0 * k.k1 + t2 * (5.0 * k.k2 + t2 * (7.0 * k.k3 + t2 * 9.0 * k.k4)));
}

}  // namespace

double PinholePixelAngleRad(const PinholeIntrinsics& k, const Eigen::Vector3d& d_cam) {
  const double on_axis = PinholePixelAngleRad(k);
  if (k.lens != Lens::kFisheye) return on_axis;
  const double theta = std::atan2(d_cam.head<2>().norm(), d_cam.z());
  if (!(theta > 1e-6)) return on_axis;  // on the axis (NaN too): both pitches are 1/f
  const double slope = FisheyeSlope(theta, k), rd = FisheyeRadius(theta, k);
  if (!(slope > 0.0) || !(rd > 0.0)) return kMaxPinholePixelAngleRad;  // at or past the fold
  const double radial = on_axis / slope;
  const double across = on_axis * std::sin(theta) / rd;
  return std::min(std::max(radial, across), kMaxPinholePixelAngleRad);
}

double FisheyeMaxAngleRad(const PinholeIntrinsics& k) {
  if (k.lens != Lens::kFisheye) return M_PI;
  const double field = k.field_of_view_rad > 0.0 ? 0.5 * k.field_of_view_rad : M_PI;
  // The last lens asked, per thread: projections ask for one lens many times over.
  thread_local double cached[5] = {NAN, NAN, NAN, NAN, M_PI};
  if (cached[0] == k.k1 && cached[1] == k.k2 && cached[2] == k.k3 && cached[3] == k.k4) {
    return std::min(cached[4], field);
  }
  // The first θ where the slope stops being positive, on steps of 0.05° then bisected.
  constexpr int kSteps = 3600;
  double max = M_PI;
  for (int i = 1; i <= kSteps; ++i) {
    const double theta = M_PI * i / kSteps;
    if (FisheyeSlope(theta, k) > 0.0) continue;
    double lo = M_PI * (i - 1) / kSteps, hi = theta;
    for (int it = 0; it < 60; ++it) {
      const double mid = 0.5 * (lo + hi);
      (FisheyeSlope(mid, k) > 0.0 ? lo : hi) = mid;
    }
    max = lo;
    break;
  }
  cached[0] = k.k1, cached[1] = k.k2, cached[2] = k.k3, cached[3] = k.k4, cached[4] = max;
  return std::min(max, field);
}

bool PinholeSees(const Eigen::Vector2d& uv_px, const PinholeIntrinsics& k) {
  if (k.lens != Lens::kFisheye) return true;
  const double rd = std::hypot((uv_px.x() - k.cx_px) / k.fx_px, (uv_px.y() - k.cy_px) / k.fy_px);
  return rd <= FisheyeRadius(FisheyeMaxAngleRad(k), k);
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
  if (k.lens == Lens::kFisheye) {
    const double r = std::hypot(p_cam.x(), p_cam.y());
    const double theta = std::atan2(r, p_cam.z());
    if (!(theta <= FisheyeMaxAngleRad(k))) return std::nullopt;  // NaN too
    if (!(r > 0.0)) return Eigen::Vector2d(k.cx_px, k.cy_px);   // on the axis
    const double s = FisheyeRadius(theta, k) / r;
    return Eigen::Vector2d(k.fx_px * s * p_cam.x() + k.cx_px, k.fy_px * s * p_cam.y() + k.cy_px);
  }
  if (!(p_cam.z() > 0.0)) return std::nullopt;
  const Eigen::Vector2d xd = Distort({p_cam.x() / p_cam.z(), p_cam.y() / p_cam.z()}, k);
  return Eigen::Vector2d(k.fx_px * xd.x() + k.cx_px, k.fy_px * xd.y() + k.cy_px);
}

Eigen::Vector3d PinholeUnproject(const Eigen::Vector2d& uv_px, const PinholeIntrinsics& k) {
  const Eigen::Vector2d xd((uv_px.x() - k.cx_px) / k.fx_px, (uv_px.y() - k.cy_px) / k.fy_px);
  if (k.lens == Lens::kFisheye) {
    const double rd = xd.norm();
    if (!(rd > 0.0)) return Eigen::Vector3d::UnitZ();
    // θ_d is increasing on [0, max]: Newton from θ = θ_d, kept inside the bracket.
    double lo = 0.0, hi = FisheyeMaxAngleRad(k);
    double theta = std::min(rd, hi);
    if (FisheyeRadius(hi, k) <= rd) {
      theta = hi;  // beyond the lens's image circle: its rim
    } else {
      for (int it = 0; it < 60; ++it) {
        const double f = FisheyeRadius(theta, k) - rd;
        (f > 0.0 ? hi : lo) = theta;
        double next = theta - f / FisheyeSlope(theta, k);
        if (!(next > lo && next < hi)) next = 0.5 * (lo + hi);
        if (std::abs(next - theta) < 1e-15) break;
        theta = next;
      }
    }
    const double s = std::sin(theta) / rd;
    return Eigen::Vector3d(s * xd.x(), s * xd.y(), std::cos(theta)).normalized();
  }
  Eigen::Vector2d x = xd;
  for (int it = 0; it < 50; ++it) {  // x ← x + (xd − D(x)): contraction for mild distortion
    const Eigen::Vector2d step = xd - Distort(x, k);
    x += step;
    if (step.squaredNorm() < 1e-30) break;
  }
  return Eigen::Vector3d(x.x(), x.y(), 1.0).normalized();
}

}  // namespace vasl::geometry

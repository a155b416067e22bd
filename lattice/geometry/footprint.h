/// @file footprint.h
/// @brief Beam footprints, incidence and range compensation (VASL-MODEL §3, §4).
/// @details Every footprint formula of the model lives here once; ingest, visibility and
///          back-projection call these functions. Lengths in metres, angles in radians.
#pragma once

#include <algorithm>
#include <cmath>

#include <Eigen/Core>

namespace vasl::geometry {

/// Default floor of cosθ when stretching a footprint along the incidence direction (§3).
inline constexpr double kCosIncidenceMin = 0.05;

/// §3: 1-σ spot radius at range r for full divergence θ, σ(r) = r·tan(θ/2), metres.
inline double SpotSigmaM(double range_m, double divergence_rad) {
  return range_m * std::tan(0.5 * divergence_rad);
}

/// §3: spot diameter d(r) = 2 r tan(θ/2), metres.
inline double SpotDiameterM(double range_m, double divergence_rad) {
  return 2.0 * SpotSigmaM(range_m, divergence_rad);
}

/// §3 incidence: cosθ = |n · v| with v the unit vector from the surface point x toward the
/// sensor origin o; n must be unit. Returns 0 when x == o.
inline double CosIncidence(const Eigen::Vector3d& n_unit, const Eigen::Vector3d& x_world,
                           const Eigen::Vector3d& o_world) {
  const Eigen::Vector3d v = o_world - x_world;
  const double r = v.norm();
  if (r <= 0.0) return 0.0;
  return std::abs(n_unit.dot(v)) / r;
}

/// A unit vector in the tangent plane of unit normal n (any one; deterministic). With
/// n.cross(AnyTangent(n)) it spans the plane in which footprints and vossel patches lie.
inline Eigen::Vector3d AnyTangent(const Eigen::Vector3d& n_unit) {
  const Eigen::Vector3d a = std::abs(n_unit.x()) < 0.9 ? Eigen::Vector3d::UnitX()
                                                       : Eigen::Vector3d::UnitY();
  return n_unit.cross(a).normalized();
}

/// The 1-σ footprint of one sample on the surface (§3), metres.
struct SurfaceFootprint {
  double major_m = 0.0;  ///< along the projection of the view direction on the tangent plane
  double minor_m = 0.0;  ///< across it
};

/// §3: s_minor = σ(r), s_major = σ(r) / max(cosθ, cosθ_min).
inline SurfaceFootprint SurfaceFootprintAt(double range_m, double divergence_rad, double cos_inc,
                                           double cos_min = kCosIncidenceMin) {
  const double s = SpotSigmaM(range_m, divergence_rad);
  return {s / std::max(cos_inc, cos_min), s};
}

/// §4: the lattice's target resolution s* = h / 2, metres.
inline double TargetResolutionM(double vossel_size_m) { return 0.5 * vossel_size_m; }

/// §4.1 matched filter: extra 1-σ width that equalises a footprint axis s to s*,
/// σ_K = sqrt(s*² − s²), or 0 when the axis is already as blurry as the lattice.
inline double MatchedFilterSigmaM(double footprint_m, double target_m) {
  return std::sqrt(std::max(0.0, target_m * target_m - footprint_m * footprint_m));
}

/// §4.2 range weight: K_range = min(1, s*/s_major) · min(1, s*/s_minor), in float or double
/// (the §7 weight kernel evaluates it in float over runs of records).
template <typename T>
inline T RangeWeight(T major_m, T minor_m, T target_m) {
  const auto share = [target_m](T s) { return s > target_m ? target_m / s : T(1); };
  return share(major_m) * share(minor_m);
}
/// The same for a footprint.
inline double RangeWeight(const SurfaceFootprint& f, double target_m) {
  return RangeWeight<double>(f.major_m, f.minor_m, target_m);
}

/// §4.3: per-channel PSFs add in quadrature.
inline double QuadratureSum(double a, double b, double c = 0.0) {
  return std::sqrt(a * a + b * b + c * c);
}

}  // namespace vasl::geometry

// VASL-MODEL §2.1 equirectangular projection, §2.2 pinhole projection.
#include "lattice/geometry/equirect.h"

#include <cmath>
#include <random>

#include <gtest/gtest.h>

#include "lattice/geometry/pinhole.h"
#include "lattice/geometry/pose.h"

namespace vasl::geometry {
namespace {

double AngleBetween(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return std::atan2(a.cross(b).norm(), a.dot(b));
}

// Claim (§2.1): π_eqr⁻¹(π_eqr(d)) = d for every direction; tolerance 1e-9 rad.
TEST(EquirectTest, ForwardInverseRoundTrip) {
  std::mt19937_64 rng(7);
  std::normal_distribution<double> n(0.0, 1.0);
  const EquirectSize size{4096, 2048};
  double worst = 0.0;
  for (int i = 0; i < 100000; ++i) {
    const Eigen::Vector3d d = Eigen::Vector3d(n(rng), n(rng), n(rng)).normalized();
    const Eigen::Vector2d uv = EquirectProject(d, size);
    ASSERT_GE(uv.x(), 0.0);
    ASSERT_LT(uv.x(), size.width_px);
    ASSERT_GE(uv.y(), 0.0);
    ASSERT_LE(uv.y(), size.height_px);
    worst = std::max(worst, AngleBetween(d, EquirectUnproject(uv.x(), uv.y(), size)));
  }
  std::printf("equirect round trip: worst angular error %.3g rad over 100000 directions\n", worst);
  EXPECT_LT(worst, 1e-9);
}

// Claim: Atan2 is the C library's atan2 to within 2 ulp of π (8.9e-16 rad) over random
// directions of every octant and scale, near the axes and the diagonals, and at the signed
// zeros and the seam (±π for y = ±0, x < 0); EquirectAngles' elevation is the C library's
// atan2(z, hypot(x, y)) to within the same, for directions of any length. (asin(z/|d|), the
// elevation before, errs by up to 2e-10 rad near the poles, where asin amplifies rounding.)
TEST(EquirectTest, Atan2AgreesWithTheCLibrary) {
  std::mt19937_64 rng(11);
  std::normal_distribution<double> n(0.0, 1.0);
  std::uniform_real_distribution<double> exponent(-30.0, 30.0), tiny(-1e-9, 1e-9);
  double worst = 0.0, worst_elevation = 0.0;
  for (int i = 0; i < 2000000; ++i) {
    double x = n(rng), y = n(rng);
    switch (i % 4) {
      case 1: y = x * (1.0 + tiny(rng)); break;   // the diagonal |y| = |x|
      case 2: y = x * tiny(rng); break;           // near the x axis
      case 3: x = y * tiny(rng); break;           // near the y axis
      default: break;
    }
    const double scale = std::exp2(exponent(rng));
    x *= scale;
    y *= scale;
    worst = std::max(worst, std::fabs(Atan2(y, x) - std::atan2(y, x)));
    const Eigen::Vector3d d(x, y, n(rng) * scale);
    const double psi = std::atan2(d.z(), std::hypot(d.x(), d.y()));
    worst_elevation = std::max(worst_elevation, std::fabs(EquirectAngles(d)[1] - psi));
  }
  std::printf("Atan2: worst |Δ| %.3g rad over 2e6 points; elevation %.3g rad\n", worst,
              worst_elevation);
  EXPECT_LE(worst, 8.9e-16);
  EXPECT_LE(worst_elevation, 8.9e-16);
  for (double x : {1.0, -1.0, 0.0, -0.0, 3.5, -2.0}) {
    for (double y : {1.0, -1.0, 0.0, -0.0, 7.0, -0.25}) {
      const double want = std::atan2(y, x), got = Atan2(y, x);
      EXPECT_NEAR(got, want, 8.9e-16) << "atan2(" << y << ", " << x << ")";
      EXPECT_EQ(std::signbit(got), std::signbit(want)) << "atan2(" << y << ", " << x << ")";
    }
  }
  EXPECT_EQ(Atan2(0.0, -1.0), M_PI);
  EXPECT_EQ(Atan2(-0.0, -1.0), -M_PI);
}

// Claim (§2.1): the axis conventions: +x at the centre column, +y to the left of it (u < W/2),
// row 0 looks up, and pixel centres sit at half-integer coordinates.
TEST(EquirectTest, AxisConventions) {
  const EquirectSize size{360, 180};
  EXPECT_NEAR(EquirectProject({1, 0, 0}, size).x(), 180.0, 1e-12);
  EXPECT_NEAR(EquirectProject({1, 0, 0}, size).y(), 90.0, 1e-12);
  EXPECT_NEAR(EquirectProject({0, 1, 0}, size).x(), 90.0, 1e-12);
  EXPECT_NEAR(EquirectProject({0, -1, 0}, size).x(), 270.0, 1e-12);
  EXPECT_NEAR(EquirectProject({0, 0, 1}, size).y(), 0.0, 1e-12);
  EXPECT_NEAR(EquirectProject({0, 0, -1}, size).y(), 180.0, 1e-12);
  // Centre of pixel (0, 0): the first column's middle azimuth, just below the zenith.
  const Eigen::Vector2d a = EquirectAngles(EquirectUnproject(0.5, 0.5, size));
  EXPECT_NEAR(a[0], M_PI - M_PI / 360.0, 1e-12);
  EXPECT_NEAR(a[1], M_PI / 2 - M_PI / 360.0, 1e-12);
}

// Claim (§2.1): columns wrap at the seam. Directions just either side of azimuth ±π land at
// u ≈ 0 and u ≈ W, and WrapColumn maps neighbours across the seam to adjacent columns.
TEST(EquirectTest, SeamWrap) {
  const EquirectSize size{1000, 500};
  const double eps = 1e-6;
  const Eigen::Vector2d left = EquirectProject({-1, std::sin(eps), 0}, size);   // φ = π − ε
  const Eigen::Vector2d right = EquirectProject({-1, -std::sin(eps), 0}, size);  // φ = −π + ε
  EXPECT_NEAR(left.x(), 0.0, 1e-3);
  EXPECT_NEAR(right.x(), size.width_px, 1e-3);
  EXPECT_LT(right.x(), size.width_px);
  // Exactly at the seam φ = −π is mapped into [0, W).
  const Eigen::Vector2d seam = EquirectProject({-1, -0.0, 0}, size);
  EXPECT_GE(seam.x(), 0.0);
  EXPECT_LT(seam.x(), size.width_px);
  EXPECT_EQ(WrapColumn(-1, 1000), 999);
  EXPECT_EQ(WrapColumn(1000, 1000), 0);
  EXPECT_EQ(WrapColumn(2003, 1000), 3);
  // The unprojection of u and u + W is the same direction.
  EXPECT_LT(AngleBetween(EquirectUnproject(3.25, 100.5, size),
                         EquirectUnproject(3.25 + size.width_px, 100.5, size)),
            1e-12);
}

// Claim (§3): θ_pix = max(Δψ, cosψ·Δφ).
TEST(EquirectTest, PixelAngleUsesMetricFactor) {
  const EquirectSize size{2000, 1000};  // Δφ = Δψ = π/1000
  EXPECT_NEAR(EquirectPixelAngleRad(0.0, size), M_PI / 1000, 1e-15);
  EXPECT_NEAR(EquirectPixelAngleRad(1.2, size), M_PI / 1000, 1e-15);  // Δψ dominates off the equator
  const EquirectSize wide{1000, 1000};  // Δφ = 2π/1000 > Δψ
  EXPECT_NEAR(EquirectPixelAngleRad(0.3, wide), std::cos(0.3) * 2 * M_PI / 1000, 1e-15);
}

// Claim (§2.2): pinhole project → unproject returns the ray, with distortion, to 1e-9 rad.
TEST(PinholeTest, ForwardInverseRoundTrip) {
  PinholeIntrinsics k;
  k.width_px = 4000;
  k.height_px = 3000;
  k.fx_px = 2900;
  k.fy_px = 2910;
  k.cx_px = 2001.5;
  k.cy_px = 1498.25;
  k.k1 = -0.08;
  k.k2 = 0.02;
  k.k3 = -0.001;
  k.p1 = 2e-4;
  k.p2 = -1e-4;
  std::mt19937_64 rng(11);
  std::uniform_real_distribution<double> u(0.0, k.width_px), v(0.0, k.height_px);
  double worst = 0.0;
  for (int i = 0; i < 20000; ++i) {
    const Eigen::Vector3d ray = PinholeUnproject({u(rng), v(rng)}, k);
    const auto uv = PinholeProject(ray * 7.3, k);
    ASSERT_TRUE(uv.has_value());
    worst = std::max(worst, AngleBetween(ray, PinholeUnproject(*uv, k)));
  }
  std::printf("pinhole round trip: worst angular error %.3g rad\n", worst);
  EXPECT_LT(worst, 1e-9);
  EXPECT_FALSE(PinholeProject({0, 0, -1}, k).has_value());
}

// Claim (pinhole.h, fisheye lens): a direction at angle θ from the axis lands at Kannala–Brandt's
// θ_d = θ(1 + k1θ² + k2θ⁴ + k3θ⁶ + k4θ⁸) along its azimuth, beyond 90° too; unproject inverts
// it to 1e-9 rad; a lens whose θ_d folds back projects nothing past the fold, and intrinsics
// that mix the two lens models are refused.
TEST(PinholeTest, FisheyeIsKannalaBrandtBeyondNinetyDegrees) {
  PinholeIntrinsics k;
  k.width_px = k.height_px = 1280;
  k.fx_px = 400.0;
  k.fy_px = 401.5;
  k.cx_px = 641.0;
  k.cy_px = 638.5;
  k.lens = Lens::kFisheye;
  k.k1 = 0.021;  // an OpenCV cv::fisheye calibration of a 200° lens
  k.k2 = -0.0048;
  k.k3 = 0.0011;
  k.k4 = 0.00005;
  ASSERT_TRUE(ValidatePinhole(k).ok());
  EXPECT_EQ(FisheyeMaxAngleRad(k), M_PI);  // this lens's θ_d grows all the way round
  // The formula written out, at θ = 100° and azimuth 30° (behind the image plane: z < 0).
  const double theta = 100.0 * M_PI / 180.0, azimuth = 30.0 * M_PI / 180.0;
  const Eigen::Vector3d d(std::sin(theta) * std::cos(azimuth), std::sin(theta) * std::sin(azimuth),
                          std::cos(theta));
  const double t2 = theta * theta;
  const double rd = theta * (1 + 0.021 * t2 - 0.0048 * t2 * t2 + 0.0011 * t2 * t2 * t2 +
                             0.00005 * t2 * t2 * t2 * t2);
  const auto uv = PinholeProject(d * 3.0, k);
  ASSERT_TRUE(uv.has_value());
  EXPECT_NEAR(uv->x(), 400.0 * rd * std::cos(azimuth) + 641.0, 1e-9);
  EXPECT_NEAR(uv->y(), 401.5 * rd * std::sin(azimuth) + 638.5, 1e-9);
  EXPECT_LT(AngleBetween(PinholeUnproject(*uv, k), d), 1e-12);
  // Round trips over the image circle of 110° from the axis.
  std::mt19937_64 rng(12);
  std::uniform_real_distribution<double> angle(0.0, 110.0 * M_PI / 180.0), turn(-M_PI, M_PI);
  double worst = 0.0;
  for (int i = 0; i < 20000; ++i) {
    const double a = angle(rng), b = turn(rng);
    const Eigen::Vector3d ray(std::sin(a) * std::cos(b), std::sin(a) * std::sin(b), std::cos(a));
    const auto px = PinholeProject(ray * 5.0, k);
    ASSERT_TRUE(px.has_value());
    worst = std::max(worst, AngleBetween(ray, PinholeUnproject(*px, k)));
  }
  std::printf("fisheye round trip to 110 degrees: worst angular error %.3g rad\n", worst);
  EXPECT_LT(worst, 1e-9);
  EXPECT_LT(AngleBetween(PinholeUnproject({641.0, 638.5}, k), Eigen::Vector3d::UnitZ()), 1e-15);

  // A lens whose θ_d folds back at the θ where 1 + 3k1θ² = 0 (k1 = −0.2: 74.5°).
  PinholeIntrinsics folded = k;
  folded.k1 = -0.2;
  folded.k2 = folded.k3 = folded.k4 = 0.0;
  const double fold = FisheyeMaxAngleRad(folded);
  EXPECT_NEAR(fold, std::sqrt(1.0 / 0.6), 1e-9);
  auto at = [](double a) { return Eigen::Vector3d(std::sin(a), 0.0, std::cos(a)); };
  EXPECT_TRUE(PinholeProject(at(fold - 1e-6), folded).has_value());
  EXPECT_FALSE(PinholeProject(at(fold + 1e-6), folded).has_value());
  // A pixel beyond the fold's radius (outside the image circle) looks along its rim.
  EXPECT_NEAR(std::acos(PinholeUnproject({641.0 + 2000.0, 638.5}, folded).z()), fold, 1e-9);

  // A field of view of 180° (a circular fisheye's image circle): nothing beyond 90° projects,
  // and a pixel sees within the circle's radius θ_d(90°) alone.
  PinholeIntrinsics circular = k;
  circular.field_of_view_rad = M_PI;
  EXPECT_DOUBLE_EQ(FisheyeMaxAngleRad(circular), M_PI / 2);
  EXPECT_TRUE(PinholeProject(at(M_PI / 2 - 1e-6), circular).has_value());
  EXPECT_FALSE(PinholeProject(at(M_PI / 2 + 1e-6), circular).has_value());
  const double half = M_PI / 2, h2 = half * half;
  const double rim_px =
      400.0 * half * (1 + h2 * (0.021 + h2 * (-0.0048 + h2 * (0.0011 + h2 * 0.00005))));
  EXPECT_TRUE(PinholeSees({641.0 + rim_px - 0.01, 638.5}, circular));
  EXPECT_FALSE(PinholeSees({641.0 + rim_px + 0.01, 638.5}, circular));
  EXPECT_TRUE(PinholeSees({641.0 + rim_px + 0.01, 638.5}, k));  // no field: the fold's radius
  circular.field_of_view_rad = 7.0;
  EXPECT_FALSE(ValidatePinhole(circular).ok());  // beyond 360°

  PinholeIntrinsics mixed = k;
  mixed.p1 = 1e-4;
  EXPECT_FALSE(ValidatePinhole(mixed).ok());
  PinholeIntrinsics brown;
  brown.fx_px = brown.fy_px = 500.0;
  brown.k4 = 0.01;  // a fisheye's coefficient on a Brown–Conrady lens
  EXPECT_FALSE(ValidatePinhole(brown).ok());
  brown.k4 = 0.0;
  brown.field_of_view_rad = 2.0;  // and its field of view
  EXPECT_FALSE(ValidatePinhole(brown).ok());
}

// Claim (§3, a fisheye's θ_pix): the angle a fisheye pixel spans, measured by unprojecting its
// neighbours one pixel away radially and across, is 1/f on the axis and grows where θ_d grows
// slower than θ; θ_pix is the larger of the two (within 0.5% of the measured angles), and a
// Brown–Conrady lens keeps §3's pitch over focal length everywhere.
TEST(PinholeTest, FisheyePixelAngleFollowsTheLensAwayFromItsAxis) {
  PinholeIntrinsics k;
  k.width_px = k.height_px = 2048;
  k.fx_px = k.fy_px = 600.0;
  k.cx_px = k.cy_px = 1024.0;
  k.lens = Lens::kFisheye;
  k.k1 = -0.03;  // θ_d grows slower than θ away from the axis (fold beyond 180°)
  k.k2 = 0.001;
  ASSERT_TRUE(ValidatePinhole(k).ok());
  const double f = 600.0;
  EXPECT_DOUBLE_EQ(PinholePixelAngleRad(k, Eigen::Vector3d::UnitZ()), 1.0 / f);
  const double azimuth = 0.7;
  double at_100 = 0.0;
  for (double deg : {5.0, 30.0, 60.0, 90.0, 100.0, 120.0}) {
    const double theta = deg * M_PI / 180.0;
    const Eigen::Vector3d d(std::sin(theta) * std::cos(azimuth),
                            std::sin(theta) * std::sin(azimuth), std::cos(theta));
    const auto uv = PinholeProject(d, k);
    ASSERT_TRUE(uv.has_value());
    const Eigen::Vector2d radial(std::cos(azimuth), std::sin(azimuth));
    const Eigen::Vector2d across(-std::sin(azimuth), std::cos(azimuth));
    // One pixel's angle along each direction, as the mean of half a pixel either side.
    const double measured_radial =
        AngleBetween(PinholeUnproject(*uv + 0.5 * radial, k), PinholeUnproject(*uv - 0.5 * radial, k));
    const double measured_across =
        AngleBetween(PinholeUnproject(*uv + 0.5 * across, k), PinholeUnproject(*uv - 0.5 * across, k));
    const double theta_pix = PinholePixelAngleRad(k, d);
    std::printf("fisheye pixel at %5.1f deg: %.3e rad radially, %.3e across, theta_pix %.3e "
                "(%.3f x the axis's)\n", deg, measured_radial, measured_across, theta_pix,
                theta_pix * f);
    EXPECT_NEAR(theta_pix, std::max(measured_radial, measured_across),
                5e-3 * std::max(measured_radial, measured_across));
    EXPECT_GE(theta_pix, 1.0 / f);
    if (deg == 100.0) at_100 = theta_pix;
  }
  EXPECT_GT(at_100 * f, 1.2);  // a fifth wider than on the axis there: worth following
  // Past a lens's fold a pixel spans without bound: held at the cap.
  PinholeIntrinsics folded = k;
  folded.k1 = -0.2;
  folded.k2 = 0.0;
  const double fold = FisheyeMaxAngleRad(folded);
  EXPECT_EQ(PinholePixelAngleRad(folded, Eigen::Vector3d(std::sin(fold + 0.01), 0.0,
                                                         std::cos(fold + 0.01))),
            kMaxPinholePixelAngleRad);
  // Brown–Conrady: §3's pitch over focal length at any direction in the image.
  PinholeIntrinsics brown;
  brown.fx_px = 500.0;
  brown.fy_px = 520.0;
  brown.k1 = -0.1;
  EXPECT_DOUBLE_EQ(PinholePixelAngleRad(brown, Eigen::Vector3d(0.4, -0.3, 1.0)), 1.0 / 510.0);
}

// Claim (§2): a pose maps sensor to world and back; NaN in a pose is rejected.
TEST(PoseTest, RoundTripAndValidation) {
  auto pose = MakePose({1, 2, 3}, {0.1, -0.2, 0.3, 0.9});
  ASSERT_TRUE(pose.ok());
  const Eigen::Vector3d p(0.4, -5, 2);
  EXPECT_LT((pose->WorldToSensor(pose->SensorToWorld(p)) - p).norm(), 1e-12);
  EXPECT_EQ(MakePose({NAN, 0, 0}, {0, 0, 0, 1}).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(MakePose({0, 0, 0}, {0, 0, 0, 0}).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(MakePose({0, 0, 0}, {0, NAN, 0, 1}).status().code(),
            absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace vasl::geometry

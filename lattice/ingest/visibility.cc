#include "lattice/ingest/visibility.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstring>
#include <limits>
#include <memory>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

namespace vasl::ingest {
namespace {

uint32_t FloatBits(float f) {
  uint32_t u;
  std::memcpy(&u, &f, 4);
  return u;
}
float BitsFloat(uint32_t u) {
  float f;
  std::memcpy(&f, &u, 4);
  return f;
}

}  // namespace

geometry::EquirectSize DepthPanoramaSize(double pitch_rad, int max_width_px) {
  int height = int(std::lround(M_PI / std::max(pitch_rad, 1e-6)));
  height = std::clamp(height, 32, max_width_px / 2);
  return {2 * height, height};
}

DepthPanorama RenderDepthPanorama(const records::VosselGeometry& g, const geometry::Pose& pose,
                                  const geometry::EquirectSize& size, double divergence_rad,
                                  const std::vector<uint8_t>* splat_only) {
  DepthPanorama out;
  out.pose = pose;
  out.size = size;
  const int W = size.width_px, H = size.height_px;
  const size_t npix = size_t(W) * H;
  std::unique_ptr<std::atomic<uint32_t>[]> depth(new std::atomic<uint32_t>[npix]);
  const uint32_t inf_bits = FloatBits(std::numeric_limits<float>::infinity());
  for (size_t p = 0; p < npix; ++p) depth[p].store(inf_bits, std::memory_order_relaxed);

  // Pixel-centre directions, separable: d = (cosψ cosφ, cosψ sinφ, sinψ).
  std::vector<double> cos_phi(W), sin_phi(W), cos_psi(H), sin_psi(H);
  for (int i = 0; i < W; ++i) {
    const double phi = 2.0 * M_PI * (0.5 - (i + 0.5) / W);
    cos_phi[i] = std::cos(phi);
    sin_phi[i] = std::sin(phi);
  }
  for (int j = 0; j < H; ++j) {
    const double psi = M_PI * (0.5 - (j + 0.5) / H);
    cos_psi[j] = std::cos(psi);
    sin_psi[j] = std::sin(psi);
  }
  const double h = g.vossel_size_m;
  const double sphere_m = 0.5 * std::sqrt(3.0) * h;  // bounding sphere of a vossel (§5)
  const double dpsi = geometry::ElevationPitchRad(size), dphi = geometry::AzimuthPitchRad(size);
  const Eigen::Matrix3d R_sensor_world = pose.q_world_sensor.conjugate().toRotationMatrix();

  tbb::parallel_for(tbb::blocked_range<size_t>(0, g.size(), 1024), [&](const tbb::blocked_range<size_t>& r) {
    for (size_t k = r.begin(); k != r.end(); ++k) {
      if (splat_only != nullptr && !(*splat_only)[k]) continue;
      const Eigen::Vector3d centre_w = h * Eigen::Vector3d(g.coord[k].x(), g.coord[k].y(), g.coord[k].z());
      const Eigen::Vector3d c_s = R_sensor_world * (centre_w - pose.o_world);
      const double range = c_s.norm();
      if (range <= sphere_m) continue;  // the sensor sits inside this vossel
      const Eigen::Vector3d d = c_s / range;
      const Eigen::Vector3d x_s =
          R_sensor_world * (g.FrameCentroid(k).cast<double>() - pose.o_world);
      const Eigen::Vector3d n_s = R_sensor_world * g.FrameNormal(k).cast<double>();
      const bool has_plane = n_s.squaredNorm() > 0.5;
      const double plane_d = n_s.dot(x_s);
      // The splat: the vossel's bounding sphere dilated by the footprint σ(r) = r·tan(θ/2) (§3).
      const double sigma_m = geometry::SpotSigmaM(range, divergence_rad);
      const double a = std::asin(std::min(1.0, (sphere_m + sigma_m) / range));
      const double cos_a = std::cos(a);
      const double half_cell_m = 0.5 * h + sigma_m;
      const Eigen::Vector2d uv = geometry::EquirectProject(d, size);
      const double psi = std::asin(std::clamp(d.z(), -1.0, 1.0));
      // The pixels whose centre (i + ½, j + ½) can lie within a of d: rows within a in
      // elevation, columns within the cap's widest azimuth half-width, asin(sin a / cos ψ).
      // Floor and ceil keep the bounds conservative; the cap test below decides.
      const double rows = a / dpsi;
      const int j0 = std::max(0, int(std::floor(uv.y() - 0.5 - rows)));
      const int j1 = std::min(H - 1, int(std::ceil(uv.y() - 0.5 + rows)));
      const double cos_psi_c = std::cos(psi);
      const bool pole = std::abs(psi) + a >= M_PI / 2 || std::sin(a) >= cos_psi_c;
      const double cols = pole ? double(W) : std::asin(std::sin(a) / cos_psi_c) / dphi;
      const bool all_cols = 2.0 * cols + 2.0 >= double(W);
      const int i0 = all_cols ? 0 : int(std::floor(uv.x() - 0.5 - cols));
      const int i1 = all_cols ? W - 1 : int(std::ceil(uv.x() - 0.5 + cols));
      for (int j = j0; j <= j1; ++j) {
        for (int ii = i0; ii <= i1; ++ii) {
          const int i = geometry::WrapColumn(ii, W);
          const Eigen::Vector3d q(cos_psi[j] * cos_phi[i], cos_psi[j] * sin_phi[i], sin_psi[j]);
          if (q.dot(d) < cos_a) continue;
          double t = range;
          if (has_plane) {
            // Surfel splat: the range where the pixel's ray crosses the vossel's plane, kept only
            // where that crossing lies inside the vossel's cell dilated by σ; a ray that grazes
            // the plane outside the vossel does not see it, and silhouettes are not inflated.
            const double nq = n_s.dot(q);
            if (std::abs(nq) < 1e-9) continue;
            t = plane_d / nq;
            if (!(t > 0.0)) continue;
            const Eigen::Vector3d off_w = R_sensor_world.transpose() * (t * q - c_s);
            if (off_w.cwiseAbs().maxCoeff() > half_cell_m) continue;
          }
          const uint32_t bits = FloatBits(float(t));
          std::atomic<uint32_t>& cell = depth[size_t(j) * W + i];
          uint32_t cur = cell.load(std::memory_order_relaxed);
          while (bits < cur && !cell.compare_exchange_weak(cur, bits, std::memory_order_relaxed)) {
          }
        }
      }
    }
  });
  out.depth_m.resize(npix);
  for (size_t p = 0; p < npix; ++p) out.depth_m[p] = BitsFloat(depth[p].load(std::memory_order_relaxed));
  return out;
}

void MaskOutsideCone(DepthPanorama& depth, const Eigen::Vector3d& axis, double half_angle_rad) {
  if (half_angle_rad >= M_PI) return;
  const int W = depth.size.width_px, H = depth.size.height_px;
  const double cos_max = std::cos(half_angle_rad);
  const Eigen::Vector3d a = axis.normalized();
  tbb::parallel_for(0, H, [&](int j) {
    for (int i = 0; i < W; ++i) {
      const Eigen::Vector3d d = geometry::EquirectUnproject(i + 0.5, j + 0.5, depth.size);
      if (d.dot(a) < cos_max) depth.depth_m[size_t(j) * W + i] = 0.0f;
    }
  });
}

void DilateDepthPanorama(DepthPanorama& depth, int radius_px, int row_begin, int row_end) {
  if (radius_px <= 0) return;
  const int W = depth.size.width_px, H = depth.size.height_px;
  row_begin = std::clamp(row_begin, 0, H);
  row_end = row_end < 0 ? H : std::clamp(row_end, row_begin, H);
  if (row_begin >= row_end) return;
  // Separable min filter: rows (wrapping), then columns (clamped); the row pass covers the rows
  // the column pass reads.
  std::vector<float> tmp(depth.depth_m.size());
  tbb::parallel_for(std::max(0, row_begin - radius_px), std::min(H, row_end + radius_px), [&](int j) {
    const float* row = &depth.depth_m[size_t(j) * W];
    for (int i = 0; i < W; ++i) {
      float m = row[i];
      for (int d = -radius_px; d <= radius_px; ++d) m = std::min(m, row[geometry::WrapColumn(i + d, W)]);
      tmp[size_t(j) * W + i] = m;
    }
  });
  tbb::parallel_for(row_begin, row_end, [&](int j) {
    for (int i = 0; i < W; ++i) {
      float m = tmp[size_t(j) * W + i];
      for (int d = -radius_px; d <= radius_px; ++d) m = std::min(m, tmp[size_t(std::clamp(j + d, 0, H - 1)) * W + i]);
      depth.depth_m[size_t(j) * W + i] = m;
    }
  });
}

std::vector<float> ComputeVisibility(const records::VosselGeometry& g, const DepthPanorama& depth,
                                     double tau_m, const std::vector<uint8_t>* only,
                                     int slope_pixels) {
  // PCF samples over the vossel's patch: a 4×4 grid and the centre. 17 samples make V a
  // multiple of 1/17, which the record's 8-bit `vis` stores exactly (code 15·lit of 255), so no
  // V ≥ V_min test a profile can set flips between ingest and a reweight from disk (§7).
  constexpr int kGrid = 4;
  constexpr int kSamples = kGrid * kGrid + 1;
  std::vector<float> vis(g.size(), 0.0f);
  const double h = g.vossel_size_m;
  const Eigen::Matrix3d R_sensor_world = depth.pose.q_world_sensor.conjugate().toRotationMatrix();
  const int W = depth.size.width_px, H = depth.size.height_px;
  const double pixel_rad =
      slope_pixels *
      std::max(geometry::AzimuthPitchRad(depth.size), geometry::ElevationPitchRad(depth.size));
  tbb::parallel_for(tbb::blocked_range<size_t>(0, g.size(), 1024), [&](const tbb::blocked_range<size_t>& r) {
    for (size_t k = r.begin(); k != r.end(); ++k) {
      if (only != nullptr && !(*only)[k]) continue;
      const Eigen::Vector3d x = g.FrameCentroid(k).cast<double>();
      Eigen::Vector3d n = g.FrameNormal(k).cast<double>();
      const Eigen::Vector3d to_sensor = depth.pose.o_world - x;
      if (to_sensor.squaredNorm() == 0.0) continue;
      if (n.squaredNorm() < 0.5) n = to_sensor.normalized();
      const Eigen::Vector3d t1 = geometry::AnyTangent(n), t2 = n.cross(t1);
      const double range_k = to_sensor.norm();
      const double tolerance_m = SlopeScaledToleranceM(tau_m, range_k, pixel_rad,
                                                       std::abs(n.dot(to_sensor)) / range_k);
      int lit = 0;
      for (int sample = 0; sample < kSamples; ++sample) {
        {
          const int a = sample / kGrid, b = sample % kGrid;  // sample kGrid² is the centre
          const double sa = sample == kGrid * kGrid ? 0.0 : ((a + 0.5) / kGrid - 0.5) * h;
          const double sb = sample == kGrid * kGrid ? 0.0 : ((b + 0.5) / kGrid - 0.5) * h;
          const Eigen::Vector3d p_s = R_sensor_world * (x + sa * t1 + sb * t2 - depth.pose.o_world);
          const double range = p_s.norm();
          const Eigen::Vector2d uv = geometry::EquirectProject(p_s, depth.size);
          const int i = geometry::WrapColumn(int(std::floor(uv.x())), W);
          const int j = std::clamp(int(std::floor(uv.y())), 0, H - 1);
          if (depth.At(i, j) >= range - tolerance_m) ++lit;
        }
      }
      vis[k] = float(lit) / float(kSamples);
    }
  });
  return vis;
}

}  // namespace vasl::ingest

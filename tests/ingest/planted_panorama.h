// Panoramas with sensor artefacts planted at known pixels (VASL-MODEL §9), for the detectors'
// tests: sharp textures, bright sources with a known bloom and a known flare veil.
#pragma once

#include <algorithm>
#include <cmath>
#include <vector>

#include "lattice/geometry/linear_image.h"

namespace vasl::ingest {
namespace {

/// A bright source: a disk of brightness B (× the clip level) whose bloom adds
/// B·exp(−d/λ) at a distance d from its edge (the planted truth), a little warm.
struct Source {
  double cx, cy, radius_px, brightness, lambda_px;
  /// Flare: a veil of glare·(1 + (d/α)²)^−β at a distance d from the centre (0: none).
  double glare = 0.0, glare_alpha_px = 1.0, glare_beta = 1.0;
  double Glare(double x, double y) const {
    const double d = std::hypot(x - cx, y - cy) / glare_alpha_px;
    return glare > 0.0 ? glare * std::pow(1.0 + d * d, -glare_beta) : 0.0;
  }
};

/// A planted panorama: the image, and per pixel its surface's own light (brightest channel)
/// and the bloom and glare added to it.
struct Planted {
  geometry::LinearImage image;
  std::vector<float> surface;
  std::vector<float> bloom;
  std::vector<float> glare;
};

/// Sharp textures (clip = 1): checkers of 7×11 px between albedos 0.25 and 0.45, a band of 1-px
/// stripes (0.15 / 0.55) and a dark band (0.03), lit at 0.8; `sheet` adds a white rectangle at
/// the clip level with no bloom (a clipped surface, not a source).
Planted MakePanorama(int w, int h, const std::vector<Source>& sources, bool sheet) {
  Planted out;
  geometry::LinearImage& img = out.image;
  img.width_px = w;
  img.height_px = h;
  img.channels = 3;
  img.clip_value = 1.0f;
  img.pixels.resize(size_t(w) * h * 3);
  out.surface.resize(size_t(w) * h);
  out.bloom.resize(size_t(w) * h);
  out.glare.resize(size_t(w) * h);
  const float tint[3] = {1.0f, 0.9f, 0.8f};
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      const size_t p = size_t(y) * w + x;
      double albedo = ((x / 7 + y / 11) % 2) ? 0.45 : 0.25;
      if (y >= h / 2 && y < h / 2 + 40) albedo = (x % 2) ? 0.55 : 0.15;
      if (y >= h - 60) albedo = 0.03;
      const bool white = sheet && x >= 500 && x < 560 && y >= 330 && y < 360;
      double bloom = 0.0, glare = 0.0;
      for (const Source& s : sources) {
        // Columns wrap: a source near the seam lights both sides of it.
        const double dx = std::min(std::abs(x + 0.5 - s.cx), w - std::abs(x + 0.5 - s.cx));
        const double d = std::hypot(dx, y + 0.5 - s.cy) - s.radius_px;
        bloom += d <= 0.0 ? s.brightness : s.brightness * std::exp(-d / s.lambda_px);
        glare += s.Glare(s.cx + dx, y + 0.5);
      }
      const double surface = white ? 1.0 : 0.8 * albedo;
      out.surface[p] = float(surface);
      out.bloom[p] = float(bloom);
      out.glare[p] = float(glare);
      for (int c = 0; c < 3; ++c) {
        img.pixels[3 * p + c] = float(std::min(1.0, surface + tint[c] * (bloom + glare)));
      }
    }
  }
  return out;
}

/// The share planted bloom adds to pixel p's own light; 0 where the pixel is clipped (no
/// blend can recover it: its confidence is 0 and it is left out of the comparison).
double BloomShare(const Planted& planted, size_t p) {
  for (int c = 0; c < 3; ++c) {
    if (planted.image.pixels[3 * p + c] >= 0.999f) return 0.0;
  }
  return planted.bloom[p] / planted.surface[p];
}

/// Sources from barely over the clip level to 64× over it, small to large, on the checkers,
/// the stripes and the dark band.
std::vector<Source> PlantedSources() {
  return {{150, 120, 3, 1.5, 2.5}, {400, 200, 5, 4.0, 2.5}, {700, 300, 8, 16.0, 3.0},
          {900, 100, 12, 64.0, 3.5}, {300, 280, 4, 8.0, 2.0}, {620, 480, 6, 12.0, 3.0}};
}

}  // namespace
}  // namespace vasl::ingest

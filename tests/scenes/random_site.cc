#include "tests/scenes/random_site.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace vasl::scenes {
namespace {

using Eigen::Vector3d;
using Eigen::Vector3f;

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr int kRoomFaces = kBoxSideCount;  // 0–5: the room's faces

// SplitMix64: the same sequence on every machine and standard library.
class Draws {
 public:
  explicit Draws(uint64_t seed) : state_(seed * 0x9e3779b97f4a7c15ull + 0x632be59bd9b4e019ull) {}
  uint64_t Next() {
    uint64_t z = (state_ += 0x9e3779b97f4a7c15ull);
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
    return z ^ (z >> 31);
  }
  /// Uniform in [lo, hi).
  double Uniform(double lo, double hi) { return lo + (hi - lo) * double(Next() >> 11) * 0x1p-53; }

 private:
  uint64_t state_;
};

// A hash of a face id to [0, 1): its texture's phases and colours.
double FaceHash(int face, int k) {
  Draws d(uint64_t(face) * 131 + uint64_t(k) + 7);
  return d.Uniform(0.0, 1.0);
}

}  // namespace

double OrientedBox::DistanceTo(const Vector3d& x_world) const {
  const Vector3d p = R_world_box.transpose() * (x_world - centre_m);
  Vector3d d;
  for (int a = 0; a < 3; ++a) d[a] = std::max(std::abs(p[a]) - half_m[a], 0.0);
  return d.norm();
}

RandomSite::RandomSite(uint64_t seed, int boxes, int stations, bool outdoor)
    : open_sky_(outdoor) {
  Draws draw(seed);
  // The room: 4-9 m × 3-7 m × 2.4-4 m (a yard: 30-60 m × 20-40 m × 3-6 m), its corner off the
  // lattice's grid; boxes scale with it.
  const double scale = outdoor ? 5.0 : 1.0;
  const Vector3d size = outdoor ? Vector3d(draw.Uniform(30.0, 60.0), draw.Uniform(20.0, 40.0),
                                           draw.Uniform(3.0, 6.0))
                                : Vector3d(draw.Uniform(4.0, 9.0), draw.Uniform(3.0, 7.0),
                                           draw.Uniform(2.4, 4.0));
  room_.min_m = Vector3d(draw.Uniform(-3.0, 3.0), draw.Uniform(-3.0, 3.0), draw.Uniform(-0.5, 0.5));
  room_.max_m = room_.min_m + size;
  for (int b = 0; b < boxes; ++b) {
    OrientedBox box;
    // One box in four is a plate thinner than a 5 cm vossel; the others 0.1-1.6 m a side.
    const bool plate = draw.Uniform(0.0, 1.0) < 0.25;
    box.half_m = Vector3d(scale * draw.Uniform(0.05, 0.8), scale * draw.Uniform(0.05, 0.8),
                          plate ? draw.Uniform(0.005, 0.02) : scale * draw.Uniform(0.05, 0.8));
    const double yaw = draw.Uniform(-M_PI, M_PI);
    const double tilt = draw.Uniform(0.0, 1.0) < 0.5 ? draw.Uniform(0.0, 0.7) : 0.0;
    const double tilt_axis = draw.Uniform(-M_PI, M_PI);
    box.R_world_box =
        (Eigen::AngleAxisd(tilt, Vector3d(std::cos(tilt_axis), std::sin(tilt_axis), 0.0)) *
         Eigen::AngleAxisd(yaw, Vector3d::UnitZ()))
            .toRotationMatrix();
    box.centre_m = Vector3d(draw.Uniform(room_.min_m.x(), room_.max_m.x()),
                            draw.Uniform(room_.min_m.y(), room_.max_m.y()),
                            draw.Uniform(0.0, 1.0) < 0.5
                                ? room_.min_m.z() + box.half_m.z()  // standing (about)
                                : draw.Uniform(room_.min_m.z() + 0.3, room_.max_m.z() - 0.3));
    boxes_.push_back(box);
  }
  // Stations and novel views: rejection sampling in the room, clear of every surface, camera
  // included.
  auto place = [&](std::vector<geometry::Pose>& out, int count) {
    for (int tries = 0; tries < 10000 && int(out.size()) < count; ++tries) {
      const Vector3d o(draw.Uniform(room_.min_m.x(), room_.max_m.x()),
                       draw.Uniform(room_.min_m.y(), room_.max_m.y()),
                       draw.Uniform(room_.min_m.z() + 0.8, room_.min_m.z() + 2.0));
      const double yaw = draw.Uniform(-M_PI, M_PI);
      const double tilt = draw.Uniform(0.0, kMaxTiltRad);
      const double tilt_axis = draw.Uniform(-M_PI, M_PI);
      geometry::Pose pose;
      pose.o_world = o;
      pose.q_world_sensor =
          Eigen::Quaterniond(
              Eigen::AngleAxisd(tilt, Vector3d(std::cos(tilt_axis), std::sin(tilt_axis), 0.0)) *
              Eigen::AngleAxisd(yaw, Vector3d::UnitZ()))
              .normalized();
      if (Clearance(o) < kClearanceM ||
          Clearance(CameraPoseForStation(pose).o_world) < kClearanceM) {
        continue;
      }
      out.push_back(pose);
    }
  };
  place(stations_, stations);
  place(novel_views_, 2);
}

double RandomSite::Clearance(const Vector3d& x) const {
  double c = kInf;
  for (int a = 0; a < 3; ++a) {
    c = std::min(c, x[a] - room_.min_m[a]);
    if (!(open_sky_ && a == 2)) c = std::min(c, room_.max_m[a] - x[a]);
  }
  for (const OrientedBox& box : boxes_) c = std::min(c, box.DistanceTo(x));
  return c;
}

SceneHit RandomSite::Intersect(const Vector3d& o, const Vector3d& d, double t_max_m) const {
  SceneHit hit;
  double t_best = kInf;
  int face_best = kFaceNone;
  Vector3d n_best = Vector3d::Zero();
  // The room: the ray leaves through the nearest wall it heads to (kBoxSide* order).
  for (int a = 0; a < 3; ++a) {
    if (d[a] == 0.0) continue;
    const bool to_max = d[a] > 0.0;
    if (open_sky_ && a == 2 && to_max) continue;  // the sky
    const double t = ((to_max ? room_.max_m[a] : room_.min_m[a]) - o[a]) / d[a];
    if (open_sky_ && a < 2 && o.z() + t * d.z() > room_.max_m.z()) continue;  // over the wall
    if (t < t_best) {
      t_best = t;
      face_best = 2 * a + (to_max ? 1 : 0);
      n_best = Vector3d::Zero();
      n_best[a] = to_max ? -1.0 : 1.0;
    }
  }
  // Boxes, each in its own frame (seen from outside only).
  for (size_t b = 0; b < boxes_.size(); ++b) {
    const OrientedBox& box = boxes_[b];
    const Eigen::Matrix3d Rt = box.R_world_box.transpose();
    const Aabb local{-box.half_m, box.half_m};
    const BoxEntry e = RayEntersBox(local, Rt * (o - box.centre_m), Rt * d);
    if (e.valid && e.t_m < t_best) {
      t_best = e.t_m;
      face_best = kRoomFaces + kBoxSideCount * int(b) + e.side;
      n_best = box.R_world_box * BoxSideNormal(e.side);
    }
  }
  if (face_best == kFaceNone || !(t_best > 0.0) || t_best > t_max_m) return hit;
  hit.valid = true;
  hit.t_m = t_best;
  hit.x_world = o + t_best * d;
  if (face_best < kRoomFaces) {  // onto the wall's plane exactly
    const int a = face_best / 2;
    hit.x_world[a] = face_best % 2 ? room_.max_m[a] : room_.min_m[a];
  }
  hit.face = face_best;
  hit.n_world = n_best;
  hit.albedo_linear = Albedo(hit.x_world, face_best);
  hit.reflectance = Luminance(hit.albedo_linear);
  return hit;
}

Vector3f RandomSite::Albedo(const Vector3d& x, int face) const {
  if (face < 0 || face >= kRoomFaces + kBoxSideCount * int(boxes_.size())) {
    return Vector3f::Constant(0.05f);
  }
  // A sinusoid field along two of the face's own directions (wavelengths 0.4-1.2 m), over its
  // own base colour: smooth (no feature finer than 0.3 m).
  Vector3d k1, k2;
  for (int a = 0; a < 3; ++a) {
    k1[a] = FaceHash(face, a) - 0.5;
    k2[a] = FaceHash(face, 3 + a) - 0.5;
  }
  k1 *= 2.0 * M_PI / ((0.4 + 0.8 * FaceHash(face, 6)) * std::max(1e-3, k1.norm()));
  k2 *= 2.0 * M_PI / ((0.4 + 0.8 * FaceHash(face, 7)) * std::max(1e-3, k2.norm()));
  const double field = 0.55 + 0.30 * std::sin(k1.dot(x) + 6.28 * FaceHash(face, 8)) +
                       0.15 * std::cos(k2.dot(x) + 6.28 * FaceHash(face, 9));
  Vector3f rgb;
  for (int c = 0; c < 3; ++c) {
    const double base = 0.35 + 0.65 * FaceHash(face, 10 + c);
    rgb[c] = float(0.05 + 0.9 * std::clamp(base * field, 0.0, 1.0));
  }
  return rgb;
}

}  // namespace vasl::scenes

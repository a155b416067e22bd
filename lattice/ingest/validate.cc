#include "lattice/ingest/validate.h"

#include <algorithm>
#include <cmath>
#include <set>

#include "absl/strings/str_cat.h"

namespace vasl::ingest {

absl::Status ValidatePose(const geometry::Pose& pose, const std::string& what) {
  const Eigen::Vector4d q = pose.q_world_sensor.coeffs();
  if (!pose.o_world.allFinite() || !q.allFinite() || std::abs(q.norm() - 1.0) > 1e-6) {
    return absl::InvalidArgumentError(
        absl::StrCat(what, ": pose must have a finite position and a finite unit quaternion"));
  }
  return absl::OkStatus();
}

absl::Status ValidateText(const std::string& what, const std::string& text, size_t max_bytes,
                          bool may_be_empty) {
  if ((text.empty() && !may_be_empty) || text.size() > max_bytes) {
    return absl::InvalidArgumentError(absl::StrCat(what, " must have ", may_be_empty ? 0 : 1,
                                                   "-", max_bytes, " bytes, got ", text.size()));
  }
  for (unsigned char c : text) {
    if (c < 0x20 || c == 0x7f) {
      return absl::InvalidArgumentError(
          absl::StrCat(what, " has a control character (byte ", int(c), "); use printable text"));
    }
  }
  return absl::OkStatus();
}

absl::StatusOr<std::vector<ImageHeader>> ValidateScan(const ScanInput& scan, const ScanLimits& limits) {
  const auto bad = [&scan](const std::string& what) {
    return absl::InvalidArgumentError(absl::StrCat("scan '", scan.scan_name, "': ", what));
  };
  if (absl::Status s = ValidateText("the scan id", scan.scan_name, 128); !s.ok()) return s;
  if (absl::Status s = ValidateText("the rig name", scan.rig, 128, true); !s.ok()) return s;
  if (absl::Status s = ValidatePose(scan.pose, "scan '" + scan.scan_name + "'"); !s.ok()) return s;
  const LidarData& lidar = scan.lidar;
  if (lidar.xyz_sensor_m.size() % 3 != 0) return bad("LiDAR xyz array length is not a multiple of 3");
  const size_t n = lidar.xyz_sensor_m.size() / 3;
  const bool cameras = std::any_of(scan.panoramas.begin(), scan.panoramas.end(),
                                   [](const PanoramaData& p) { return !p.visual_reference; });
  if (n == 0 && !cameras) {
    return bad("no LiDAR points and no camera images: a scan needs returns to place vossels, or "
               "images to colour the vossels the project has (visual references alone colour "
               "nothing)");
  }
  if (int64_t(n) > limits.max_points_per_scan) {
    return absl::ResourceExhaustedError(absl::StrCat("scan '", scan.scan_name, "' has ", n,
                                                     " points, above the limit of ",
                                                     limits.max_points_per_scan));
  }
  for (float v : lidar.xyz_sensor_m) {
    if (!std::isfinite(v)) return bad("a LiDAR point has a NaN or infinite coordinate");
  }
  if (!lidar.intensity.empty() && lidar.intensity.size() != n) {
    return bad(absl::StrCat("intensity has ", lidar.intensity.size(), " values for ", n, " points"));
  }
  for (float v : lidar.intensity) {
    if (!std::isfinite(v)) return bad("a LiDAR intensity is NaN or infinite");
  }
  if (!lidar.rgb.empty() && lidar.rgb.size() != 3 * n) {
    return bad(absl::StrCat("point colour has ", lidar.rgb.size(), " values for ", n,
                            " points (3 per point: r, g, b)"));
  }
  for (float v : lidar.rgb) {
    if (!std::isfinite(v) || v < 0.0f) return bad("a point colour is negative, NaN or infinite");
  }
  if (!lidar.grid_cell.empty() || lidar.grid_rows != 0 || lidar.grid_columns != 0) {
    if (lidar.grid_rows <= 0 || lidar.grid_columns <= 0 ||
        int64_t(lidar.grid_rows) * lidar.grid_columns > int64_t{1} << 32) {
      return bad(absl::StrCat("the range grid is ", lidar.grid_rows, "x", lidar.grid_columns,
                              ": rows and columns must be > 0 and at most 2^32 cells in all"));
    }
    if (lidar.grid_cell.size() != n) {
      return bad(absl::StrCat("the range grid gives ", lidar.grid_cell.size(), " cells for ", n,
                              " points (one row and column per point)"));
    }
    const uint64_t cells = uint64_t(lidar.grid_rows) * uint64_t(lidar.grid_columns);
    for (uint32_t c : lidar.grid_cell) {
      if (c >= cells) {
        return bad(absl::StrCat("a point's grid cell lies outside the ", lidar.grid_rows, "x",
                                lidar.grid_columns, " range grid"));
      }
    }
  }
  if (n > 0 && !(lidar.divergence_rad > 0.0 && lidar.divergence_rad <= 0.1)) {
    return bad("LiDAR divergence_rad must lie in (0, 0.1] radians");
  }
  if (int64_t(scan.panoramas.size()) > limits.max_panoramas_per_scan) {
    return absl::ResourceExhaustedError(absl::StrCat("scan has ", scan.panoramas.size(),
                                                     " panoramas, above the limit of ",
                                                     limits.max_panoramas_per_scan));
  }
  std::set<std::string> names;
  std::vector<ImageHeader> images;
  for (const PanoramaData& pano : scan.panoramas) {
    if (absl::Status s = ValidateText("a panorama name", pano.name, 128); !s.ok()) return s;
    const std::string what = absl::StrCat("panorama '", pano.name, "'");
    if (pano.name.empty() || !names.insert(pano.name).second) {
      return bad("panorama names must be non-empty and unique within the scan");
    }
    if (absl::Status s = ValidatePose(pano.pose, what); !s.ok()) return bad(std::string(s.message()));
    if (pano.encoded_image.empty()) return bad(what + ": no image bytes");
    if (int64_t(pano.encoded_image.size()) > limits.max_image_bytes) {
      return absl::ResourceExhaustedError(absl::StrCat(what, " has ", pano.encoded_image.size(),
                                                       " bytes, above the limit of ",
                                                       limits.max_image_bytes));
    }
    absl::StatusOr<ImageHeader> image = ProbeImage(pano.encoded_image, limits.max_image_pixels);
    if (!image.ok()) {
      return absl::Status(image.status().code(),
                          absl::StrCat("scan '", scan.scan_name, "', ", what, ": ", image.status().message()));
    }
    if (pano.visual_reference) {  // kept as sent: it must be an image, nothing more
      images.push_back(*image);
      continue;
    }
    if (!pano.encoded_mask.empty()) {
      if (int64_t(pano.encoded_mask.size()) > limits.max_image_bytes) {
        return absl::ResourceExhaustedError(absl::StrCat(what, ": its mask has ",
                                                         pano.encoded_mask.size(),
                                                         " bytes, above the limit of ",
                                                         limits.max_image_bytes));
      }
      absl::StatusOr<ImageHeader> mask = ProbeImage(pano.encoded_mask, limits.max_image_pixels);
      if (!mask.ok()) {
        return absl::Status(mask.status().code(),
                            absl::StrCat("scan '", scan.scan_name, "', ", what, ": its mask: ",
                                         mask.status().message()));
      }
      if (mask->width_px != image->width_px || mask->height_px != image->height_px) {
        return bad(absl::StrCat(what, ": its mask is ", mask->width_px, "x", mask->height_px,
                                ", not the image's ", image->width_px, "x", image->height_px));
      }
    }
    if (pano.modality != records::Modality::kRgb && pano.modality != records::Modality::kIr) {
      return bad(what + ": modality must be rgb or ir");
    }
    if (!(pano.angular_resolution_rad >= 0.0 && pano.angular_resolution_rad < 0.1)) {
      return bad(what + ": angular_resolution_rad must lie in [0, 0.1) (0: from the image size)");
    }
    if (pano.cylinder && (pano.pinhole || pano.sphere)) {
      return bad(what + ": a cylindrical panorama is neither a pinhole photo nor given a sphere "
                        "window (its window follows from its cylinder)");
    }
    if (pano.pinhole) {
      if (pano.sphere) {
        return bad(what + ": a pinhole photo has no sphere (a sphere window is for an "
                          "equirectangular panorama that spans part of it)");
      }
      if (absl::Status s = geometry::ValidatePinhole(*pano.pinhole); !s.ok()) {
        return bad(absl::StrCat(what, ": ", s.message()));
      }
      images.push_back(*image);
      continue;
    }
    if (pano.sphere || pano.cylinder) {  // a part of the sphere: the panorama is the sphere's
      SphereWindow window;
      if (pano.cylinder) {
        absl::StatusOr<CylinderPlacement> placed =
            CylinderWindow(*pano.cylinder, image->width_px, image->height_px);
        if (!placed.ok()) return bad(absl::StrCat(what, ": ", placed.status().message()));
        window = placed->window;
      } else {
        window = *pano.sphere;
        if (absl::Status s = CheckSphereWindow(window, image->width_px, image->height_px);
            !s.ok()) {
          return bad(absl::StrCat(what, ": ", s.message()));
        }
      }
      const int64_t pixels = int64_t(window.width_px) * window.height_px;
      if (pixels > limits.max_image_pixels) {
        return absl::ResourceExhaustedError(absl::StrCat(
            what, ": its ", window.width_px, "x", window.height_px, " sphere has ", pixels,
            " pixels, above the limit of ", limits.max_image_pixels));
      }
      ImageHeader sphere = *image;
      sphere.width_px = window.width_px;
      sphere.height_px = window.height_px;
      images.push_back(sphere);
      continue;
    }
    const double aspect = double(image->width_px) / image->height_px;
    if (aspect < 1.95 || aspect > 2.05) {
      return bad(absl::StrCat(what, " is ", image->width_px, "x", image->height_px,
                              ": an equirectangular panorama spans 360°×180°, so its width must "
                              "be twice its height (give intrinsics for a pinhole photo; give a "
                              "panorama that spans less its place in the sphere, or pad it with "
                              "transparent pixels, alpha 0)"));
    }
    images.push_back(*image);
  }
  return images;
}

absl::StatusOr<LinearImage> DecodePanorama(const ScanInput& scan, size_t index,
                                           int64_t max_image_pixels) {
  const PanoramaData& pano = scan.panoramas.at(index);
  absl::StatusOr<LinearImage> image =
      DecodeImage(pano.encoded_image, pano.modality == records::Modality::kIr, max_image_pixels);
  if (!image.ok()) {
    return absl::Status(image.status().code(),
                        absl::StrCat("scan '", scan.scan_name, "', panorama '", pano.name, "': ",
                                     image.status().message()));
  }
  if (!pano.encoded_mask.empty() && !pano.visual_reference) {
    if (absl::Status s = ApplyMask(pano.encoded_mask, max_image_pixels, *image); !s.ok()) {
      return absl::Status(s.code(), absl::StrCat("scan '", scan.scan_name, "', panorama '",
                                                 pano.name, "': ", s.message()));
    }
  }
  if ((pano.sphere || pano.cylinder) && !pano.visual_reference && !pano.pinhole) {
    if (absl::Status s = pano.cylinder
                             ? CylinderToSphere(*pano.cylinder, max_image_pixels, *image)
                             : PlaceInSphere(*pano.sphere, max_image_pixels, *image);
        !s.ok()) {
      return absl::Status(s.code(), absl::StrCat("scan '", scan.scan_name, "', panorama '",
                                                 pano.name, "': ", s.message()));
    }
  }
  return image;
}

}  // namespace vasl::ingest

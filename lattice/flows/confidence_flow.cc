/// @file confidence_flow.cc
/// @brief The confidence maps of a scan's cameras (VASL-MODEL §9), for a person to look at:
///        each camera's stored image decoded again and its artefacts found as at ingest.
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "lattice/flows/flows.h"
#include "lattice/ingest/artefacts.h"

namespace vasl::flows {

absl::StatusOr<std::vector<SourceConfidence>> ScanConfidence(
    const store::ProjectStore& store, const std::vector<store::ScanInfo>& scans,
    const std::string& project, const std::string& scan, int64_t max_pixels) {
  for (const store::ScanInfo& s : scans) {
    if (s.name != scan) continue;
    std::vector<SourceConfidence> out;
    for (const store::SourceInfo& src : s.sources) {
      const bool camera = (src.modality == records::Modality::kRgb ||
                           src.modality == records::Modality::kIr) && !IsPointColour(src);
      if (!camera) continue;
      const ingest::CameraSource cam = StoredCamera(store, src, s.batch, max_pixels);
      absl::StatusOr<ingest::LinearImage> image = cam.load();
      if (!image.ok()) return image.status();
      // As at ingest (ingest::CameraRecords): a panorama's columns wrap, a photo's do not.
      const ingest::SaturationMap saturation = ingest::DetectSaturation(*image, !cam.pinhole);
      SourceConfidence& c = out.emplace_back();
      c.source_id = src.id;
      c.source = src.name;
      c.width_px = image->width_px;
      c.height_px = image->height_px;
      ArtefactMap& map = c.artefacts.emplace_back();
      map.artefact = "saturation";
      map.flagged_pixels = saturation.clipped_pixels;
      map.soft_pixels = saturation.halo_pixels;
      map.regions = saturation.blobs;
      map.max_extent_px = saturation.max_halo_radius_px;
      map.covered_fraction = saturation.CoveredFraction(image->width_px, image->height_px);
      absl::StatusOr<std::string> png =
          ingest::EncodeConfidencePng(saturation.conf, image->width_px, image->height_px);
      if (!png.ok()) return png.status();
      map.png = std::move(*png);
    }
    return out;
  }
  return absl::NotFoundError(absl::StrCat("project '", project, "' has no scan '", scan, "'"));
}

}  // namespace vasl::flows

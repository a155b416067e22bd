/// @file confidence_flow.cc
/// @brief The confidence maps of a scan's cameras (VASL-MODEL §9), for a person to look at:
///        each camera's stored image decoded again and its artefacts found as at ingest.
#include <cmath>
#include <map>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "lattice/flows/flows.h"
#include "lattice/fusion/lens.h"
#include "lattice/reweight/profiles.h"
#include "lattice/ingest/artefacts.h"

namespace vasl::flows {

absl::StatusOr<std::vector<SourceConfidence>> ScanConfidence(
    const store::ProjectStore& store, const std::vector<store::ScanInfo>& scans,
    const std::string& project, const std::string& scan, int64_t max_pixels) {
  // §9 lens dirt and fog: the latest map that lists a source applies to it.
  absl::StatusOr<std::vector<fusion::LensMap>> lens_maps = reweight::ListLensMaps(store);
  if (!lens_maps.ok()) return lens_maps.status();
  std::map<int32_t, const fusion::LensMap*> lens_of;
  for (const fusion::LensMap& map : *lens_maps) {
    for (const auto& [source, gain] : map.source_gain) lens_of[source] = &map;
  }
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
      const ingest::ArtefactMaps maps = ingest::DetectArtefacts(*image, !cam.pinhole);
      SourceConfidence& c = out.emplace_back();
      c.source_id = src.id;
      c.source = src.name;
      c.width_px = image->width_px;
      c.height_px = image->height_px;
      const int w = image->width_px, h = image->height_px;
      // Each map's coverage: pixels at 0 and in (0, 1), regions, widest reach.
      auto coverage = [&](const char* artefact, int64_t flagged, int64_t soft, int regions,
                          int extent_px) {
        ArtefactMap map;
        map.artefact = artefact;
        map.flagged_pixels = flagged;
        map.soft_pixels = soft;
        map.regions = regions;
        map.max_extent_px = extent_px;
        map.covered_fraction = double(flagged + soft) / (double(w) * double(h));
        return map;
      };
      ArtefactMap saturation =
          coverage("saturation", maps.saturation.clipped_pixels, maps.saturation.halo_pixels,
                   maps.saturation.blobs, maps.saturation.max_halo_radius_px);
      ArtefactMap smear = coverage("smear", 0, maps.smear.soft_pixels, maps.smear.columns, 0);
      smear.smear_offset = maps.smear.max_offset;
      ArtefactMap flare = coverage("flare", maps.flare.invalid_pixels, maps.flare.soft_pixels,
                                   maps.flare.sources, maps.flare.max_radius_px);
      ArtefactMap codec = coverage("codec", 0, maps.codec.soft_pixels, 0, 0);
      codec.jpeg_quality = maps.codec.jpeg ? maps.codec.quality : 0.0;
      codec.chroma_subsampled = maps.codec.chroma_subsampled;
      // Fringing is a correction: its map shows where the correction moved a pixel's colour.
      geometry::LinearImage corrected = *image, moved;
      ArtefactMap fringing =
          coverage("fringing", 0, ingest::CorrectChannelShift(corrected, maps.fringing, &moved),
                   0, int(std::ceil(maps.fringing.max_offset_px)));
      if (maps.fringing.found) {
        fringing.channel_offsets_px = {maps.fringing.dx[0], maps.fringing.dy[0],
                                       maps.fringing.dx[2], maps.fringing.dy[2]};
      }
      const std::pair<ArtefactMap*, const geometry::LinearImage*> found[] = {
          {&saturation, &maps.saturation.conf}, {&smear, &maps.smear.conf},
          {&flare, &maps.flare.conf},
          {&codec, &maps.codec.conf}, {&fringing, &moved}};
      for (const auto& [map, conf] : found) {
        absl::StatusOr<std::string> png = ingest::EncodeConfidencePng(*conf, w, h);
        if (!png.ok()) return png.status();
        map->png = std::move(*png);
        c.artefacts.push_back(std::move(*map));
      }
      if (auto it = lens_of.find(src.id); it != lens_of.end()) {
        // The factors fusion puts on conf[dirt] and conf[fog] at each pixel
        // (fusion::AdjustForLens), read at the image's own colours; the maps' pixels are the
        // image as sent.
        const fusion::LensMap& lens = *it->second;
        geometry::LinearImage ones;
        ones.width_px = w;
        ones.height_px = h;
        ones.channels = 1;
        ones.pixels.assign(size_t(w) * h, 1.0f);
        struct Factor {
          const char* name;
          geometry::LinearImage conf;
          int64_t flagged = 0, soft = 0;
        };
        Factor factors[2] = {{"dirt", ones}, {"fog", std::move(ones)}};
        const float sx = float(src.width_px > 0 ? src.width_px : w) / float(w);
        const float sy = float(src.height_px > 0 ? src.height_px : h) / float(h);
        for (int y = 0; y < h; ++y) {
          for (int x = 0; x < w; ++x) {
            const size_t p = size_t(y) * w + x;
            float value[3] = {0, 0, 0};
            for (int ch = 0; ch < std::min(3, image->channels); ++ch) {
              value[ch] = image->pixels[p * image->channels + ch];
            }
            const float uv[2] = {(float(x) + 0.5f) * sx, (float(y) + 0.5f) * sy};
            const fusion::LensFactors f =
                fusion::AdjustForLens(lens, lens.source_gain.at(src.id), uv, value);
            const float v[2] = {f.dirt, f.fog};
            for (int k = 0; k < 2; ++k) {
              factors[k].conf.pixels[p] = v[k];
              factors[k].flagged += v[k] == 0.0f;
              factors[k].soft += v[k] > 0.0f && v[k] < 1.0f;
            }
          }
        }
        for (Factor& factor : factors) {
          ArtefactMap map = coverage(factor.name, factor.flagged, factor.soft, 0, 0);
          map.lens_map = lens.id;
          absl::StatusOr<std::string> png = ingest::EncodeConfidencePng(factor.conf, w, h);
          if (!png.ok()) return png.status();
          map.png = std::move(*png);
          c.artefacts.push_back(std::move(map));
        }
      }
    }
    return out;
  }
  return absl::NotFoundError(absl::StrCat("project '", project, "' has no scan '", scan, "'"));
}

}  // namespace vasl::flows

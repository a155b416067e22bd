/// @file lens.h
/// @brief Lens dirt and fog (VASL-MODEL §9): a camera's persistent multiplicative dirt map
///        D < 1 and additive veil v > 0 in its image, applied to the records of the sources it
///        was found for when they are fused (§7).
/// @details A rig's camera that looks through dirt or a fogged window puts the same error on
///          the same pixels of every frame: an observation at pixel p of source m is
///          ```
///          C_obs = g_m · (D(p) · C + v(p))          per channel
///          ```
///          with C the scene's colour and g_m the frame's exposure gain. A LensMap holds D and v
///          on a grid of cells over the image (bilinear between cell centres, clamped at the
///          borders) and g_m per source. Fusion reads the record's uv (§6) and
///          - corrects its value: C = (C_obs − g_m·v) / D, per channel, at least 0;
///          - multiplies its conf[dirt] factor by D_min · (1 − g_m·v / C_obs)_min over the
///            channels, clamped to [0, 1]: the share of the light that came from the scene,
///            dimmed by the dirt, so that κ_dirt weighs it as any other §9 factor.
///          Records keep what this needs (scan, uv, value), so a map found later applies to
///          scans ingested before it by a reweight, never a re-ingest.
///
///          Maps are project data kept in the catalog (store::ProjectStore::PutLensMap); a
///          profile lists the maps it applies (WeightingProfile::lens_maps) and carries them,
///          resolved, in WeightingProfile::lens.
#pragma once

#include <array>
#include <cstdint>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "lattice/records/records.h"

namespace vasl::fusion {

/// Dirt and veil of one rig's camera over one period (§9).
struct LensMap {
  int64_t id = 0;            ///< catalog id (0 until stored)
  std::string rig;           ///< the rig (scan metadata)
  std::string camera;        ///< the camera's source name in its scans
  int image_w = 0;           ///< the camera image's size, pixels
  int image_h = 0;
  int grid_w = 0;            ///< cells across and down; a cell spans image_w/grid_w pixels
  int grid_h = 0;
  /// D per cell and channel, grid_h·grid_w·3, row-major; 1 where no dirt was found.
  std::vector<float> transmission;
  /// v per cell and channel (record units, before the gain), same layout; 0: no veil.
  std::vector<float> veil;
  /// g_m per source id the map applies to, per channel: the period's frames.
  std::map<int32_t, std::array<float, records::kValueChannels>> source_gain;
  std::string period;        ///< what the period is, for people (e.g. the capture-time span)
  std::string created_utc;   ///< when the catalog stored it (not in its text)

  /// D and v at continuous pixel coordinates (u, v), bilinear between cell centres.
  void Sample(float u, float v, float* d, float* veil_out) const;
  /// The fraction of the image's cells with D < 1 or v > 0.
  double DirtShare() const;
  double VeilShare() const;
};

/// The factors a lens map puts on a record's confidence (§9), each in [0, 1]: dirt, min over
/// channels of D (the light that reached the sensor), on conf[dirt]; fog, min over channels of
/// the share of the observed colour that is the scene's (1 − g·v/C_obs), on conf[fog].
struct LensFactors {
  float dirt = 1.0f;
  float fog = 1.0f;
  bool operator!=(const LensFactors& o) const { return dirt != o.dirt || fog != o.fog; }
};

/// The §9 lens adjustment of one RGB record: its value corrected in place (per channel),
/// C = (C_obs − g·v)/D, and the factors on its confidence. `gain` is the source's g_m.
LensFactors AdjustForLens(const LensMap& map,
                          const std::array<float, records::kValueChannels>& gain,
                          const float* uv, float* value);

/// The maps a profile applies, resolved: per source id the map that covers it.
struct LensTable {
  std::vector<std::shared_ptr<const LensMap>> maps;
  /// Source id → index into `maps`; a source listed by two maps takes the later one.
  std::map<int32_t, size_t> by_source;
  /// A table of `maps`, later maps taking precedence over earlier ones for a source.
  static std::shared_ptr<const LensTable> Of(std::vector<std::shared_ptr<const LensMap>> maps);
};

/// The catalog text of a map: one "key values..." line per field, floats with 9 digits (they
/// read back bit for bit).
std::string LensMapToText(const LensMap& map);
/// Reads LensMapToText's output. DATA_LOSS for text it did not write or sizes that disagree.
absl::StatusOr<LensMap> LensMapFromText(const std::string& text);

}  // namespace vasl::fusion

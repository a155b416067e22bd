/// @file artefacts.h
/// @brief Sensor artefacts as per-pixel confidence (VASL-MODEL §9), found in a decoded image
///        and sampled into its records' confidence factors at ingest.
#pragma once

#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"

#include "lattice/geometry/linear_image.h"

namespace vasl::ingest {

/// Saturation and blooming (§9) found in one image.
struct SaturationMap {
  /// Per pixel, the confidence that its value is its surface's own light: 0 where a channel is
  /// at the clip level (≥ 0.999 of it), 1 − Δ/L in a bloom halo (Δ the bloom, L the pixel's
  /// brightest channel over the clip level), 1 elsewhere; one channel. No pixels: 1 everywhere
  /// (nothing clipped, or no clip level).
  geometry::LinearImage conf;
  int64_t clipped_pixels = 0;
  int64_t halo_pixels = 0;  ///< pixels outside the clipped regions with confidence < 1
  int blobs = 0;            ///< connected clipped regions (8-neighbours)
  int max_halo_radius_px = 0;

  /// Share of the image's pixels with confidence < 1.
  double CoveredFraction(int width_px, int height_px) const;
};

/// Finds saturation and blooming (§9) in `image` (linear, with its clip level).
/// @details A pixel is clipped when any channel reaches 0.999 of the clip level. Clipped pixels
///          form blobs (8-connected). Around each blob the light a sensor spills (blooming, and
///          the optics' veiling near a source) is measured, not assumed: every pixel within
///          R_b = 4·r_b + 8 pixels of the blob (r_b = √(area/π), capped at a quarter of the
///          image height) falls into the ring ⌊distance⌋ of its nearest clipped pixel (an exact
///          Euclidean distance transform). A ring's 10% quantile of brightness, made
///          non-increasing outward, is the blob's radial profile; its excess over the lowest
///          ring (the surround's own level) is the ring's bloom Δ_k, counted above 0.01 of the
///          clip (noise). Bloom lifts a ring's darkest pixels as much as its brightest, while
///          texture leaves them at the surround's darkest level: so texture that does not fall
///          off around a blob is not taken for bloom, and the halo grows with how far the
///          source is over the clip level, as the image shows it. A pixel whose bloom adds more
///          than a tenth to its own light (1 − Δ/L < 1/1.1) is halo, with confidence 1 − Δ/L.
///          At most 16 M (ring, direction) bins are measured, the largest blobs first: an
///          image speckled with clipped specks beyond them keeps those specks at 0, without
///          halos, in bounded memory.
///          Columns wrap across a panorama's seam for the blobs (`wrap`); the distance
///          transform does not (a halo cut at the seam is measured on its own side).
///          Exposure (a halo's growth with exposure time) is in the image already; column
///          smear is not modelled.
/// Parallel over rows and columns (TBB).
SaturationMap DetectSaturation(const geometry::LinearImage& image, bool wrap);

/// Flare (§9): the veiling glare bright sources spread over the image.
struct FlareMap {
  /// Per pixel, the confidence that its value is its surface's own light: 0 where the glare is
  /// at least half the pixel's light (invalid: no record takes colour from it), 1 − G/L where
  /// it adds more than a tenth (G the glare, L the pixel's brightest channel over the clip
  /// level), 1 elsewhere and on the clipped sources themselves (saturation's); one channel.
  /// No pixels: 1 everywhere (no source with a measurable veil).
  geometry::LinearImage conf;
  int sources = 0;               ///< bright sources whose veil was measured
  int64_t invalid_pixels = 0;    ///< pixels at 0
  int64_t soft_pixels = 0;       ///< pixels in (0, 1)
  int max_radius_px = 0;         ///< farthest affected pixel from its nearest source

  /// Share of the image's pixels with confidence < 1.
  double CoveredFraction(int width_px, int height_px) const;
};

/// A flare confidence map's value at and below which a pixel is invalid (its soft values are
/// at least 1/2): a sampling kernel's point reading below this half of 1/2 takes no colour.
inline constexpr float kFlareInvalidBelow = 0.25f;

/// Finds flare (§9) in `image` (linear, with its clip level): bright sources and the veiling
/// glare around each, measured from the image and modelled.
/// @details The sources are the clipped blobs (DetectSaturation's), the largest
///          kMaxFlareSources first. Around each, from its bloom reach R_b (4·r_b + 8 px) out to
///          8·R_b (at most half the image height), the pixels fall into 24 rings spaced evenly in
///          log distance from the blob's centroid, in 8 directions; each (ring, direction) bin
///          gives its dark floor (10% quantile) and its contrast (90% − 10% quantile). A bin
///          whose 90% quantile is at half the clip level or more is not measured (a bright
///          region, where the clip cuts the contrast).
///          - Per direction, the floor's fall from ring to ring, each the median of the falls
///            within two rings (a veil falls smoothly; the scene's edges step at one ring or
///            two). Per ring, the median over the directions (a veil falls alike in all of
///            them), summed from the outermost ring inward: the floor's excess q(d), and the
///            contrast's c(d) the same way.
///          - A veil lifts the floor without lifting the contrast, while a surface lit more
///            brightly toward the source lifts both in proportion, and a scene may brighten
///            slowly toward it: q(d) is fitted by k·c(d) + s·ln(d_far/d) + a·(f(d) − f(d_far))
///            with k, s, a ≥ 0 and f(d) = (1 + (d/α)²)^−β a Moffat profile (α from R_b/16
///            to 4·R_b, β from 1 to 3: glare falls at least as the inverse square of the
///            distance beyond a core, as the CIE glare equation's 1/θ²), by least squares of
///            relative errors. The veil a·f(d) is cut to the darkest direction's floor at every ring
///            (the veil is light every pixel holds). Of the (α, β) whose fit is within a
///            quarter of the best, the one of lowest β is kept (the slower tail).
///          - A source whose surround is measured in under 3/4 of the directions (a window,
///            the sky), whose fit leaves over 5% of the excess unexplained (the scene's own
///            falloff), or whose veil at R_b is under the noise (0.01 of the clip level) has no
///            flare; a smaller blob within a kept source's R_b is a fragment of it.
///          The glare G at a pixel is the sum of its sources' veils at max(d, R_b/2) (the core
///          within R_b/2 is not extrapolated), out to where each falls under half the noise (at
///          most the image height away). A pixel whose glare is at least half its light is
///          invalid (confidence 0); one where it adds more than a tenth gets 1 − G/L.
///          Columns wrap across a panorama's seam (`wrap`). Bounded work: at most 1 M pixels
///          per source are measured (a stride over larger discs).
/// Parallel over sources and rows (TBB).
FlareMap DetectFlare(const geometry::LinearImage& image, bool wrap);

/// Chromatic fringing (§9): where each channel's edges lie against green's, over the image.
struct ChannelShift {
  bool found = false;      ///< an offset of at least 0.2 px somewhere: the correction applies
  int64_t edges = 0;       ///< edge samples measured (both axes)
  int width_px = 0, height_px = 0;
  bool wrap = false;       ///< a panorama: columns wrap
  /// Image-wide median offsets (pixels) by channel R, G, B (green's 0): channel c's edges lie
  /// at green's + (dx[c], dy[c]).
  double dx[3] = {0.0, 0.0, 0.0}, dy[3] = {0.0, 0.0, 0.0};
  /// The field: per tile of a tiles_x × tiles_y grid, red's and blue's (dx, dy); a tile with
  /// too few edges holds the image-wide median.
  int tiles_x = 0, tiles_y = 0;
  std::vector<float> tile_dx, tile_dy;  ///< 2 per tile (red, blue), row-major tiles
  double max_offset_px = 0.0;           ///< the largest tile offset's length

  /// Channel c's offset at pixel coordinates (x, y), bilinear between tile centres; (0, 0)
  /// for green or when nothing was found.
  std::pair<double, double> Offset(int channel, double x, double y) const;
};

/// Estimates chromatic fringing (§9) in a linear RGB image.
/// @details At high-contrast edges (green's central difference along x or y at least 0.08 of
///          the clip level, twice that along the other axis, a local maximum along its own,
///          and red and blue changing the same way by at least a quarter of it), each channel's
///          centroid of its gradient over ±3 px along the axis; red's and blue's offsets against
///          green's are the medians per tile of an 8 × 4 grid (the image-wide median for a tile
///          with under 100 edges), along x from vertical edges and along y from horizontal ones.
///          Fewer than 200 edges on an axis, or offsets all under 0.2 px, are no fringing.
///          Parallel over rows (TBB).
ChannelShift EstimateChannelShift(const geometry::LinearImage& image, bool wrap);

/// Applies `shift` to `image` (a correction, §9): red and blue are resampled (bilinear) at each
/// pixel plus their offset, so their edges land on green's. Returns the pixels whose colour the
/// correction moved by more than a tenth of their light; with `changed`, a map of them for a
/// person to look at (1 − the share moved where over a tenth, 1 elsewhere; empty when nothing
/// was found). Does nothing unless shift.found and the sizes agree. Parallel over rows (TBB).
/// With a row range only rows [row_begin, row_end) are corrected (and counted); the others
/// keep their raw values (a reader of those rows alone, SampledRows).
/// Of a band of the image (LinearImage::row_origin), rows it holds alone are corrected, and
/// only when it also holds the ChannelShiftRowPad rows either side that they read (clamped to
/// the image).
int64_t CorrectChannelShift(geometry::LinearImage& image, const ChannelShift& shift,
                            geometry::LinearImage* changed = nullptr, int row_begin = 0,
                            int row_end = -1);
/// How many rows beyond a run of rows CorrectChannelShift reads to correct it, in an image of
/// `height_px` rows.
int ChannelShiftRowPad(const ChannelShift& shift, int height_px);

/// Codec artefacts (§9): what a JPEG's coding left in the image.
struct CodecMap {
  /// Per pixel, the confidence that its value is its surface's own light: 1 − e/L where the
  /// codec's expected error e adds more than a tenth to the pixel's light L, 1 elsewhere; one
  /// channel. No pixels: 1 everywhere (not a JPEG).
  geometry::LinearImage conf;
  bool jpeg = false;               ///< the image came from a JPEG whose tables were read
  double quality = 0.0;            ///< the IJG quality its luma table corresponds to, 1..100
  bool chroma_subsampled = false;  ///< its chroma was coded at a lower resolution (4:2:0, 4:2:2)
  int64_t soft_pixels = 0;         ///< pixels below 1

  /// Share of the image's pixels with confidence < 1.
  double CoveredFraction(int width_px, int height_px) const;
};

/// Finds codec artefacts (§9) in an image decoded from a JPEG (LinearImage::coding).
/// @details In the codec's own domain (8-bit sRGB codes as JFIF Y'CbCr, 8×8 blocks from the
///          corner; chroma at its own resolution), each plane's blocks are taken again: a
///          coefficient that survived quantisation carries an error of q²/12 (q its step in the
///          file's table); one quantised to 0 lost E[F² | |F| < q/2] under a Laplacian whose
///          scale the share of that frequency's coefficients that survived names, among blocks
///          of as much detail (a block with an edge rings more than a smooth one; one with no
///          surviving detail in proportion to its neighbours' DC differences, which tell a flat
///          block from one that lost everything). Their sum over 64 is the block's mean square
///          error (blocking and ringing). Under subsampled chroma, the decoder's chroma ramps
///          across a colour edge, and a pixel's distance to the nearer of the chroma's extremes
///          within a chroma sample's reach is what the averaging took from it. Each channel's
///          error, in linear terms at its own level, over the pixel's light is a share; a pixel
///          whose largest is over a tenth gets 1 − share. Not a JPEG: empty. Parallel (TBB).
CodecMap DetectCodec(const geometry::LinearImage& image);

/// Readout smear (§9): a CCD reading its columns out while a bright source shines adds the
/// same light to every pixel of the source's columns.
struct SmearMap {
  /// Per pixel 1 − s/L in a smeared column where the smear s adds more than a tenth of the
  /// pixel's light L (over the clip level), 1 elsewhere; one channel. Empty: 1 everywhere.
  geometry::LinearImage conf;
  int columns = 0;            ///< columns found smeared
  std::vector<float> column_offset;  ///< per column its smear (0: none); empty: no column
  int64_t soft_pixels = 0;    ///< pixels below 1
  double max_offset = 0.0;    ///< the largest smear, a fraction of the clip level

  double CoveredFraction(int width_px, int height_px) const;
};

/// Finds readout smear (§9) through the clipped blobs of `image`.
/// @details For every column a clipped blob covers (blobs under an eighth of the image wide),
///          the lift of each row over the mean of the nearest columns on either side that no
///          blob covers (two pixels further out) is taken, on the rows away from every blob of
///          the column and its bloom reach. Smear is uniform along the column: the lift's
///          interquartile mean over the rows above the blobs and over the rows below each
///          exceeds the noise (0.01 of the clip) and four of its standard errors, the two agree
///          within a factor of two (a lamp on a pole lifts one side only), and the column's
///          smear is the smaller. Texture lifts a column's rows as often up as down and leaves
///          that mean at 0. Smear is measured, so a CMOS camera's images, which have none, stay
///          at 1.
///          Parallel over columns (TBB).
SmearMap DetectSmear(const geometry::LinearImage& image, bool wrap);

/// Every §9 map of one image, as ingest samples them into a record's confidence factors.
struct ArtefactMaps {
  SaturationMap saturation;  ///< conf[saturation]: clipped pixels and their blooming halo
  SmearMap smear;            ///< conf[smear]: readout smear
  FlareMap flare;            ///< conf[flare], and hard invalidation
  CodecMap codec;            ///< conf[codec]
  ChannelShift fringing;     ///< a correction of the image before sampling (CorrectChannelShift)
};

/// Runs every detector over `image` (the clipped blobs found once). Parallel (TBB).
ArtefactMaps DetectArtefacts(const geometry::LinearImage& image, bool wrap);

/// A confidence map (one channel in [0, 1]; empty: 1 everywhere) of a width_px × height_px
/// image as an 8-bit grey PNG for a person to look at: 255 where the confidence is 1, 0 where
/// it is 0.
absl::StatusOr<std::string> EncodeConfidencePng(const geometry::LinearImage& conf, int width_px,
                                                int height_px);

}  // namespace vasl::ingest

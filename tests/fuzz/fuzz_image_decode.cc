/// @file fuzz_image_decode.cc
/// @brief libFuzzer harness over ingest::DecodeImage (lattice/ingest/sources.h), the decoder
///        of panoramas sent to IngestScan: the input is the encoded image (PNG, JPEG, EXR or
///        TIFF, picked by its signature; OpenImageIO decodes from memory).
/// @details Decodes with kMaxImagePixels (tests/fuzz/fuzz_limits.h) as 3 channels and, when
///          that succeeds, again as 1 channel (the IR path). Claims checked: a rejection is
///          INVALID_ARGUMENT or RESOURCE_EXHAUSTED with a message; a decoded image is non-empty,
///          within the pixel limit, has the channels asked for and width·height·channels
///          values, and both decodes agree on the size. Only vasl's code is instrumented:
///          Debian's OpenImageIO and codecs give libFuzzer no coverage, but their reads of the
///          input buffer and their allocations pass through ASan's interceptors.
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "lattice/ingest/sources.h"
#include "tests/fuzz/fuzz_check.h"
#include "tests/fuzz/fuzz_limits.h"

namespace {

void CheckImage(const vasl::ingest::LinearImage& im, int channels) {
  VASL_FUZZ_CHECK(im.width_px > 0 && im.height_px > 0 &&
                      int64_t{im.width_px} * im.height_px <= vasl::fuzz::kMaxImagePixels,
                  "decoded a ", im.width_px, "x", im.height_px, " image");
  VASL_FUZZ_CHECK(im.channels == channels, "asked for ", channels, " channels, got ",
                  im.channels);
  VASL_FUZZ_CHECK(
      im.pixels.size() == size_t(im.width_px) * size_t(im.height_px) * size_t(im.channels),
      im.pixels.size(), " values for ", im.width_px, "x", im.height_px, "x", im.channels);
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string_view bytes(reinterpret_cast<const char*>(data), size);
  absl::StatusOr<vasl::ingest::LinearImage> rgb =
      vasl::ingest::DecodeImage(bytes, /*infrared=*/false, vasl::fuzz::kMaxImagePixels);
  if (!rgb.ok()) {
    vasl::fuzz::CheckRejection(rgb.status(), "DecodeImage");
    return 0;
  }
  CheckImage(*rgb, 3);
  absl::StatusOr<vasl::ingest::LinearImage> ir =
      vasl::ingest::DecodeImage(bytes, /*infrared=*/true, vasl::fuzz::kMaxImagePixels);
  VASL_FUZZ_CHECK(ir.ok(), "decodes as RGB but not as one channel: ", ir.status().ToString());
  CheckImage(*ir, 1);
  VASL_FUZZ_CHECK(ir->width_px == rgb->width_px && ir->height_px == rgb->height_px,
                  "the two decodes disagree on the size");
  return 0;
}

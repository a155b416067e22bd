// Sources of a stored project, read back from their blobs (flows.h).
#include <cstring>

#include "absl/strings/str_cat.h"
#include "lattice/flows/flows.h"

namespace vasl::flows {

ingest::LidarSource LidarOf(const store::SourceInfo& s, int32_t batch) {
  ingest::LidarSource out;
  out.id = s.id;
  out.batch = batch;
  out.pose = s.pose;
  out.divergence_rad = s.divergence_rad;
  return out;
}

ingest::CameraSource CameraOf(const store::SourceInfo& s, int32_t batch) {
  ingest::CameraSource cam;
  cam.id = s.id;
  cam.batch = batch;
  cam.pose = s.pose;
  cam.modality = s.modality;
  cam.angular_resolution_rad = s.divergence_rad;
  return cam;
}

absl::StatusOr<ingest::LidarSource> LoadLidar(const store::ProjectStore& store,
                                              const store::SourceInfo& s, int32_t batch) {
  absl::StatusOr<std::string> bytes = store.ReadBlob(s.blob_sha256);
  if (!bytes.ok()) return bytes.status();
  if (bytes->size() % 16 != 0) {
    return absl::DataLossError(
        absl::StrCat("points blob ", s.blob_sha256, " is not a whole number of points"));
  }
  ingest::LidarSource out = LidarOf(s, batch);
  const size_t n = bytes->size() / 16;
  out.xyz_sensor_m.resize(3 * n);
  out.intensity.resize(n);
  for (size_t i = 0; i < n; ++i) {
    float rec[4];
    std::memcpy(rec, bytes->data() + i * 16, 16);
    std::copy(rec, rec + 3, &out.xyz_sensor_m[3 * i]);
    out.intensity[i] = rec[3];
  }
  return out;
}

ingest::CameraSource StoredCamera(const store::ProjectStore& store, const store::SourceInfo& src,
                                  int32_t batch, int64_t max_pixels) {
  ingest::CameraSource cam = CameraOf(src, batch);
  const store::ProjectStore* st = &store;
  cam.load = [st, src, max_pixels]() -> absl::StatusOr<ingest::LinearImage> {
    absl::StatusOr<std::string> bytes = st->ReadBlob(src.blob_sha256);
    if (!bytes.ok()) return bytes.status();
    absl::StatusOr<ingest::LinearImage> image =
        ingest::DecodeImage(*bytes, src.modality == records::Modality::kIr, max_pixels);
    if (!image.ok()) {
      return absl::DataLossError(
          absl::StrCat("stored image ", src.blob_sha256, ": ", image.status().message()));
    }
    return image;
  };
  return cam;
}

}  // namespace vasl::flows

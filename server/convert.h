/// @file convert.h
/// @brief Conversions between vasl.v1 protos and lattice types, with the validation a
///        conversion needs (poses, modalities, render sizes). No model maths here.
/// @details Errors are absl::Status naming the offending field so that a user can fix the
///          request; server/status_util.h maps them to gRPC codes.
#pragma once

#include "absl/strings/string_view.h"

#include "absl/status/statusor.h"
#include "lattice/engine.h"
#include "lattice/render/encode.h"
#include "vasl/v1/vasl.pb.h"

namespace vasl::server {

/// Proto pose -> T_world_sensor (VASL-MODEL §2). Absent position: origin; absent quaternion:
/// identity. INVALID_ARGUMENT (naming `field`) for a non-finite value or a zero quaternion.
/// An RFC 3339 time from the catalog as a Timestamp (cleared when it does not parse).
void TimestampFromIso(const std::string& iso, google::protobuf::Timestamp* out);
/// A client's Timestamp as the RFC 3339 text the catalog keeps; INVALID_ARGUMENT when out of
/// range.
absl::StatusOr<std::string> TimestampToIso(const google::protobuf::Timestamp& ts,
                                           absl::string_view field);

absl::StatusOr<geometry::Pose> PoseFromProto(const v1::Pose& pose, absl::string_view field);
void PoseToProto(const geometry::Pose& pose, v1::Pose* out);
/// The intrinsics of a pinhole camera message (width and height 0: the image's own);
/// INVALID_ARGUMENT naming `field` for a lens value this server does not know.
absl::StatusOr<geometry::PinholeIntrinsics> PinholeFromProto(const v1::PinholeCamera& camera,
                                                             absl::string_view field);

/// MODALITY_RGB / MODALITY_IR for panoramas; anything else is INVALID_ARGUMENT.
absl::StatusOr<records::Modality> PanoramaModalityFromProto(v1::Modality modality,
                                                            absl::string_view field);
v1::Modality ModalityToProto(records::Modality modality);

void ProjectToProto(const ProjectInfo& info, v1::Project* out);
/// §2.3 figures of camera `camera` as the proto carries them.
void CalibrationToProto(const std::string& camera, const records::CalibrationHealth& c,
                        v1::CalibrationHealth* out);
void VisualReferenceToProto(const store::VisualReferenceInfo& ref, v1::VisualReference* out);
void ScanToProto(const store::ScanInfo& scan, v1::Scan* out);
void AttributeToProto(const records::AttributeInfo& info, v1::RecordAttribute* out);
void VersionToProto(const store::VersionInfo& info, v1::Version* out);
/// What a change recomputed and wrote (ingest, rebuild, deletion).
void ChangeStatsToProto(const IngestResult& result, v1::ChangeStats* out);
/// Version, counts, seconds, stages and change figures of a rebuild or deletion.
void ChangeToProto(const IngestResult& result, v1::ChangeResponse* out);
/// Per-stage seconds, in order.
void StagesToProto(const std::vector<std::pair<std::string, double>>& stages,
                   google::protobuf::RepeatedPtrField<v1::StageTime>* out);

/// CreateProjectRequest -> settings (0 fields take the defaults). INVALID_ARGUMENT for a
/// non-finite or negative vossel size or a negative retention.
absl::StatusOr<store::ProjectSettings> SettingsFromProto(const v1::CreateProjectRequest& request);

/// RenderRequest -> lattice request. INVALID_ARGUMENT for a missing pose, a non-positive size,
/// a negative or non-finite eta / max range; RESOURCE_EXHAUSTED above the configured limits.
absl::StatusOr<render::RenderRequest> RenderRequestFromProto(const v1::RenderRequest& request,
                                                             const EngineLimits& limits);

/// The formats to encode, in request order, duplicates dropped; empty request: EXR only.
/// INVALID_ARGUMENT for IMAGE_FORMAT_UNSPECIFIED or an unknown value.
/// A client's profile with the model's defaults where it leaves fields unset; INVALID_ARGUMENT
/// for values out of range.
absl::StatusOr<fusion::WeightingProfile> ProfileFromProto(const v1::WeightingProfile& profile);
void ProfileToProto(const fusion::WeightingProfile& profile, const std::string& created_utc,
                    v1::WeightingProfile* out);
/// A lens map (VASL-MODEL §9); `summary` leaves its cells out.
void LensMapToProto(const fusion::LensMap& map, bool summary, v1::LensMap* out);
void RecordRowToProto(const flows::RecordRow& row, v1::RecordRow* out);

absl::StatusOr<std::vector<v1::ImageFormat>> RenderFormatsFromProto(
    const v1::RenderRequest& request);
/// A scan's confidence maps' summary (VASL-MODEL §9); the maps' bytes are streamed apart.
void ScanConfidenceToProto(const std::string& scan,
                           const std::vector<flows::SourceConfidence>& cameras,
                           v1::ScanConfidence* out);
/// The encoder of a format RenderFormatsFromProto accepted.
render::ImageFormat ImageFormatFromProto(v1::ImageFormat format);

}  // namespace vasl::server

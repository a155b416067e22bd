/// @file convert.cc
/// @brief vasl.v1 protos <-> lattice types.
#include "server/convert.h"

#include <algorithm>
#include <cmath>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "google/protobuf/util/time_util.h"
#include "lattice/ingest/validate.h"
#include "server/status_util.h"

namespace vasl::server {

void TimestampFromIso(const std::string& iso, google::protobuf::Timestamp* out) {
  // The catalog holds RFC 3339 times (UtcNowIso8601, or what TimestampToIso wrote); a time
  // that does not parse is left unset rather than made up.
  if (!google::protobuf::util::TimeUtil::FromString(iso, out)) out->Clear();
}

absl::StatusOr<std::string> TimestampToIso(const google::protobuf::Timestamp& ts,
                                           absl::string_view field) {
  using google::protobuf::util::TimeUtil;
  if (ts.seconds() < TimeUtil::kTimestampMinSeconds || ts.seconds() > TimeUtil::kTimestampMaxSeconds ||
      ts.nanos() < 0 || ts.nanos() > 999'999'999) {
    return absl::InvalidArgumentError(absl::StrCat(field, " is not a valid time (seconds ",
                                                   ts.seconds(), ", nanos ", ts.nanos(), ")"));
  }
  return google::protobuf::util::TimeUtil::ToString(ts);
}

absl::StatusOr<geometry::Pose> PoseFromProto(const v1::Pose& pose, absl::string_view field) {
  Eigen::Vector3d position_m = Eigen::Vector3d::Zero();
  if (pose.has_position_m()) {
    position_m = {pose.position_m().x(), pose.position_m().y(), pose.position_m().z()};
  }
  if (!position_m.allFinite()) {
    return absl::InvalidArgumentError(
        absl::StrCat(field, ".position_m must be finite, got (", position_m.x(), ", ",
                     position_m.y(), ", ", position_m.z(), ")"));
  }
  Eigen::Vector4d quat_xyzw(0.0, 0.0, 0.0, 1.0);
  if (pose.has_quaternion_xyzw()) {
    const v1::Quaternion& q = pose.quaternion_xyzw();
    quat_xyzw = {q.x(), q.y(), q.z(), q.w()};
  }
  absl::StatusOr<geometry::Pose> result = geometry::MakePose(position_m, quat_xyzw);
  if (!result.ok()) {
    return absl::Status(result.status().code(),
                        absl::StrCat(field, ".quaternion_xyzw: ", result.status().message()));
  }
  return result;
}

void PoseToProto(const geometry::Pose& pose, v1::Pose* out) {
  v1::Vec3* p = out->mutable_position_m();
  p->set_x(pose.o_world.x());
  p->set_y(pose.o_world.y());
  p->set_z(pose.o_world.z());
  v1::Quaternion* q = out->mutable_quaternion_xyzw();
  q->set_x(pose.q_world_sensor.x());
  q->set_y(pose.q_world_sensor.y());
  q->set_z(pose.q_world_sensor.z());
  q->set_w(pose.q_world_sensor.w());
}

absl::StatusOr<records::Modality> PanoramaModalityFromProto(v1::Modality modality,
                                                            absl::string_view field) {
  switch (modality) {
    case v1::MODALITY_RGB: return records::Modality::kRgb;
    case v1::MODALITY_IR: return records::Modality::kIr;
    default:
      return absl::InvalidArgumentError(
          absl::StrCat(field, ".modality must be MODALITY_RGB or MODALITY_IR, got ",
                       v1::Modality_IsValid(modality) ? v1::Modality_Name(modality)
                                                      : absl::StrCat(static_cast<int>(modality))));
  }
}

v1::Modality ModalityToProto(records::Modality modality) {
  switch (modality) {
    case records::Modality::kLidar: return v1::MODALITY_LIDAR;
    case records::Modality::kRgb: return v1::MODALITY_RGB;
    case records::Modality::kIr: return v1::MODALITY_IR;
    case records::Modality::kRadar: return v1::MODALITY_RADAR;
    case records::Modality::kDerived: return v1::MODALITY_DERIVED;
    default: return v1::MODALITY_UNSPECIFIED;
  }
}

void ProjectToProto(const ProjectInfo& info, v1::Project* out) {
  out->set_name(info.name);
  out->set_description(info.description);
  out->set_vossel_size_m(info.vossel_size_m);
  out->set_head_version(info.head_version);
  out->set_scan_count(info.scan_count);
  out->set_vossel_count(info.vossel_count);
  out->set_record_count(info.record_count);
  TimestampFromIso(info.created_utc, out->mutable_create_time());
  out->set_problem(RedactPaths(info.problem));
  if (info.origin_m) {
    out->mutable_origin_m()->set_x(info.origin_m->x());
    out->mutable_origin_m()->set_y(info.origin_m->y());
    out->mutable_origin_m()->set_z(info.origin_m->z());
  }
}

void CalibrationToProto(const std::string& camera, const records::CalibrationHealth& c,
                        v1::CalibrationHealth* out) {
  using V = records::CalibrationHealth::Verdict;
  out->set_camera(camera);
  out->set_lidar_source(c.lidar_source);
  out->set_verdict(c.verdict == V::kOk        ? v1::CalibrationHealth::VERDICT_OK
                   : c.verdict == V::kFlagged ? v1::CalibrationHealth::VERDICT_FLAGGED
                                              : v1::CalibrationHealth::VERDICT_UNCHECKED);
  out->set_points_in_view(c.points_in_view);
  out->set_features(c.features);
  out->set_matched(c.matched);
  out->set_cell_px(c.cell_px);
  out->set_pixel_mean_px(c.pixel_mean_px);
  out->set_pixel_p95_px(c.pixel_p95_px);
  out->set_offset_mean_m(c.offset_mean_m);
  out->set_offset_p95_m(c.offset_p95_m);
  out->set_roundtrip_mean_m(c.roundtrip_mean_m);
  out->set_roundtrip_p95_m(c.roundtrip_p95_m);
  out->set_rotation_deg(c.rotation_deg);
  out->set_note(c.note);
}

void VisualReferenceToProto(const store::VisualReferenceInfo& ref, v1::VisualReference* out) {
  out->set_name(ref.name);
  PoseToProto(ref.pose, out->mutable_pose());
  out->set_blob_sha256(ref.blob_sha256);
  out->set_width_px(ref.width_px);
  out->set_height_px(ref.height_px);
  out->set_size_bytes(ref.size_bytes);
}

void ScanToProto(const store::ScanInfo& scan, v1::Scan* out) {
  out->set_id(scan.id);
  out->set_name(scan.name);
  out->set_rig(scan.rig);
  if (!scan.captured_utc.empty()) TimestampFromIso(scan.captured_utc, out->mutable_capture_time());
  PoseToProto(scan.pose, out->mutable_pose());
  out->set_batch(scan.batch);
  out->set_version(scan.version);
  TimestampFromIso(scan.created_utc, out->mutable_create_time());
  for (const store::SourceInfo& src : scan.sources) {
    v1::Source* s = out->add_sources();
    s->set_id(src.id);
    s->set_name(src.name);
    s->set_modality(ModalityToProto(src.modality));
    PoseToProto(src.pose, s->mutable_pose());
    s->set_blob_sha256(src.blob_sha256);
    s->set_mask_sha256(src.mask_sha256);
    if (src.modality != records::Modality::kLidar) {
      s->set_projection(src.camera.empty() ? "equirect" : src.camera);
    }
    s->set_width_px(src.width_px);
    s->set_height_px(src.height_px);
    s->set_divergence_rad(src.divergence_rad);
    s->set_point_count(src.point_count);
    if (src.calibration) CalibrationToProto(src.name, *src.calibration, s->mutable_calibration());
  }
  for (const store::VisualReferenceInfo& ref : scan.visual_references) {
    VisualReferenceToProto(ref, out->add_visual_references());
  }
}

void AttributeToProto(const records::AttributeInfo& info, v1::RecordAttribute* out) {
  out->set_name(info.name);
  out->set_type(info.type);
  out->set_codec(info.codec);
  out->set_stride(info.stride);
}

absl::StatusOr<store::ProjectSettings> SettingsFromProto(const v1::CreateProjectRequest& request) {
  store::ProjectSettings settings;
  const double h = request.vossel_size_m();
  if (!std::isfinite(h) || h < 0.0) {
    return absl::InvalidArgumentError(
        absl::StrCat("vossel_size_m must be a positive number of metres, got ", h));
  }
  if (h > 0.0) settings.vossel_size_m = h;
  if (request.keep_versions() < 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("keep_versions must be >= 0, got ", request.keep_versions()));
  }
  if (request.keep_versions() > 0) settings.keep_versions = request.keep_versions();
  if (absl::Status s = ingest::ValidateText("description", request.description(), 4096, true);
      !s.ok()) {
    return s;
  }
  settings.description = request.description();
  if (request.has_origin_m()) {
    const v1::Vec3& o = request.origin_m();
    settings.origin_m = Eigen::Vector3d(o.x(), o.y(), o.z());
    if (!settings.origin_m->allFinite()) {
      return absl::InvalidArgumentError("origin_m must be a finite point, world metres");
    }
  }
  return settings;
}

absl::StatusOr<render::RenderRequest> RenderRequestFromProto(const v1::RenderRequest& request,
                                                             const EngineLimits& limits) {
  render::RenderRequest out;
  if (!request.has_pose()) {
    return absl::InvalidArgumentError("pose is required: the viewpoint of the render");
  }
  absl::StatusOr<geometry::Pose> pose = PoseFromProto(request.pose(), "pose");
  if (!pose.ok()) return pose.status();
  out.pose = *pose;
  if (request.width_px() <= 0 || request.height_px() <= 0) {
    return absl::InvalidArgumentError(absl::StrCat("width_px and height_px must be > 0, got ",
                                                   request.width_px(), "x", request.height_px()));
  }
  if (request.width_px() > limits.max_render_width_px ||
      request.height_px() > limits.max_render_height_px) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "render size ", request.width_px(), "x", request.height_px(), " exceeds the limit ",
        limits.max_render_width_px, "x", limits.max_render_height_px, " px"));
  }
  out.width_px = request.width_px();
  out.height_px = request.height_px();
  if (request.version() < 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("version must be >= 0 (0: HEAD), got ", request.version()));
  }
  out.version = request.version();
  if (!std::isfinite(request.eta()) || request.eta() < 0.0) {
    return absl::InvalidArgumentError(absl::StrCat("eta must be >= 0, got ", request.eta()));
  }
  out.eta = request.eta();
  switch (request.colour_detail()) {
    case v1::COLOUR_DETAIL_UNSPECIFIED:
    case v1::COLOUR_DETAIL_VOSSEL:
      out.colour_detail = render::ColourDetail::kVossel;
      break;
    case v1::COLOUR_DETAIL_SOURCE_IMAGES:
      out.colour_detail = render::ColourDetail::kSourceImages;
      break;
    default:
      return absl::InvalidArgumentError(
          absl::StrCat("unknown colour_detail ", int(request.colour_detail())));
  }
  if (!std::isfinite(request.max_range_m()) || request.max_range_m() < 0.0) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_range_m must be >= 0 (0: 1000 m), got ", request.max_range_m()));
  }
  if (request.max_range_m() > 0.0) out.max_range_m = request.max_range_m();
  if (request.profile_revision() < 0) {
    return absl::InvalidArgumentError("profile_revision must be >= 0 (0: the latest)");
  }
  out.profile = request.profile();
  out.profile_revision = request.profile_revision();
  if (request.layers() < 0 || request.layers() > render::kMaxLayers) {
    return absl::InvalidArgumentError(absl::StrCat("layers must lie in [0, ", render::kMaxLayers,
                                                   "] (0: 1), got ", request.layers()));
  }
  out.layers = std::max(1, request.layers());
  if (request.has_pinhole()) {
    out.projection = render::Projection::kPinhole;
    absl::StatusOr<geometry::PinholeIntrinsics> k = PinholeFromProto(request.pinhole(), "pinhole");
    if (!k.ok()) return k.status();
    out.pinhole = *k;
  }
  return out;
}

absl::StatusOr<geometry::PinholeIntrinsics> PinholeFromProto(const v1::PinholeCamera& c,
                                                             absl::string_view field) {
  geometry::PinholeIntrinsics k{0,      0,      c.fx_px(), c.fy_px(), c.cx_px(), c.cy_px(),
                                c.k1(), c.k2(), c.k3(),    c.p1(),    c.p2()};
  switch (c.lens()) {
    case v1::LENS_BROWN_CONRADY: break;
    case v1::LENS_FISHEYE: k.lens = geometry::Lens::kFisheye; break;
    default:
      return absl::InvalidArgumentError(absl::StrCat(
          field, ".lens ", int(c.lens()), " is not a lens this server knows (0: Brown-Conrady, "
          "1: fisheye)"));
  }
  k.k4 = c.k4();
  k.field_of_view_rad = c.field_of_view_deg() * M_PI / 180.0;
  return k;
}

absl::StatusOr<fusion::WeightingProfile> ProfileFromProto(const v1::WeightingProfile& p) {
  fusion::WeightingProfile out;
  out.name = p.name();
  if (p.has_alpha()) out.alpha = p.alpha();
  if (p.has_beta()) out.beta = p.beta();
  if (p.has_rho()) out.rho = p.rho();
  if (p.kappa_size() != 0) {
    if (p.kappa_size() != int(out.kappa.size()) &&
        p.kappa_size() != int(fusion::kOlderKappaCount)) {
      return absl::InvalidArgumentError(absl::StrCat(
          "profile kappa needs ", out.kappa.size(), " values (",
          absl::StrJoin(records::kConfidenceNames, ", "), "), the first ",
          fusion::kOlderKappaCount, " of them, or none; got ", p.kappa_size()));
    }
    for (int f = 0; f < p.kappa_size(); ++f) out.kappa[size_t(f)] = p.kappa(f);
  }
  if (p.has_v_min()) out.v_min = p.v_min();
  if (p.has_lambda_src()) out.lambda_src = p.lambda_src();
  if (p.has_theta_max_rad()) out.theta_max_rad = p.theta_max_rad();
  if (p.has_proximity_m()) out.proximity_m = p.proximity_m();
  out.mode = p.mode() == v1::WeightingProfile::MODE_NEAREST ? fusion::FusionMode::kNearest
                                                             : fusion::FusionMode::kBlend;
  for (const auto& [source, g] : p.scan_gain()) out.scan_gain[source] = g;
  for (const v1::ChannelGain& cg : p.channel_gain()) {
    if (cg.gain_size() < 1 || cg.gain_size() > records::kValueChannels) {
      return absl::InvalidArgumentError(absl::StrCat("channel_gain of source ", cg.source(),
                                                     " needs 1 to ", records::kValueChannels,
                                                     " gains; got ", cg.gain_size()));
    }
    std::array<double, records::kValueChannels> a;
    for (int c = 0; c < records::kValueChannels; ++c) a[size_t(c)] = cg.gain(std::min(c, cg.gain_size() - 1));
    out.channel_gain[cg.source()] = a;
  }
  out.lens_maps.assign(p.lens_maps().begin(), p.lens_maps().end());
  if (absl::Status s = fusion::ValidateProfile(out); !s.ok()) return s;
  return out;
}

void ProfileToProto(const fusion::WeightingProfile& p, const std::string& created_utc,
                    v1::WeightingProfile* out) {
  out->set_name(p.name);
  out->set_revision(p.version);
  out->set_alpha(p.alpha);
  out->set_beta(p.beta);
  out->set_rho(p.rho);
  for (double k : p.kappa) out->add_kappa(k);
  out->set_v_min(p.v_min);
  out->set_lambda_src(p.lambda_src);
  out->set_theta_max_rad(p.theta_max_rad);
  out->set_proximity_m(p.proximity_m);
  out->set_mode(p.mode == fusion::FusionMode::kNearest ? v1::WeightingProfile::MODE_NEAREST
                                                       : v1::WeightingProfile::MODE_BLEND);
  for (const auto& [source, g] : p.scan_gain) (*out->mutable_scan_gain())[source] = g;
  for (const auto& [source, a] : p.channel_gain) {
    v1::ChannelGain* cg = out->add_channel_gain();
    cg->set_source(source);
    for (double g : a) cg->add_gain(g);
  }
  for (int64_t id : p.lens_maps) out->add_lens_maps(id);
  if (!created_utc.empty()) TimestampFromIso(created_utc, out->mutable_create_time());
}

void LensMapToProto(const fusion::LensMap& m, bool summary, v1::LensMap* out) {
  out->set_id(m.id);
  out->set_rig(m.rig);
  out->set_camera(m.camera);
  out->set_period(m.period);
  out->set_image_width_px(m.image_w);
  out->set_image_height_px(m.image_h);
  out->set_grid_width(m.grid_w);
  out->set_grid_height(m.grid_h);
  if (!summary) {
    out->mutable_transmission()->Add(m.transmission.begin(), m.transmission.end());
    out->mutable_veil()->Add(m.veil.begin(), m.veil.end());
  }
  for (const auto& [source, g] : m.source_gain) {
    v1::ChannelGain* cg = out->add_source_gain();
    cg->set_source(source);
    for (float x : g) cg->add_gain(x);
  }
  out->set_dirt_share(m.DirtShare());
  out->set_veil_share(m.VeilShare());
  if (!m.created_utc.empty()) TimestampFromIso(m.created_utc, out->mutable_create_time());
}

void RecordRowToProto(const flows::RecordRow& r, v1::RecordRow* out) {
  out->set_vossel(r.vossel);
  out->set_kx(r.coord.x());
  out->set_ky(r.coord.y());
  out->set_kz(r.coord.z());
  out->mutable_centroid_m()->set_x(r.centroid_m.x());
  out->mutable_centroid_m()->set_y(r.centroid_m.y());
  out->mutable_centroid_m()->set_z(r.centroid_m.z());
  out->set_source(r.source);
  out->set_source_name(r.source_name);
  out->set_scan_id(r.scan_id);
  out->set_scan(r.scan_name);
  out->set_modality(ModalityToProto(r.modality));
  for (int c = 0; c < records::ChannelCount(r.modality); ++c) out->add_value(r.value[size_t(c)]);
  out->set_range_m(r.range_m);
  out->set_cos_inc(r.cos_inc);
  out->set_foot_major_m(r.foot_major_m);
  out->set_foot_minor_m(r.foot_minor_m);
  out->set_vis(r.vis);
  out->set_u_px(r.uv_px[0]);
  out->set_v_px(r.uv_px[1]);
  for (float c : r.conf) out->add_conf(c);
  out->set_flags(r.flags);
  out->set_batch(r.batch);
  out->set_weight(r.weight);
}

absl::StatusOr<std::vector<v1::ImageFormat>> RenderFormatsFromProto(
    const v1::RenderRequest& request) {
  std::vector<v1::ImageFormat> formats;
  for (int f : request.formats()) {
    if (f != v1::IMAGE_FORMAT_EXR && f != v1::IMAGE_FORMAT_PNG && f != v1::IMAGE_FORMAT_DEEP_EXR) {
      return absl::InvalidArgumentError(absl::StrCat(
          "formats: ", f, " is not IMAGE_FORMAT_EXR (1), IMAGE_FORMAT_PNG (2) or "
          "IMAGE_FORMAT_DEEP_EXR (3)"));
    }
    auto format = static_cast<v1::ImageFormat>(f);
    if (std::find(formats.begin(), formats.end(), format) == formats.end()) {
      formats.push_back(format);
    }
  }
  if (formats.empty()) formats.push_back(v1::IMAGE_FORMAT_EXR);
  return formats;
}

void ScanConfidenceToProto(const std::string& scan,
                           const std::vector<flows::SourceConfidence>& cameras,
                           v1::ScanConfidence* out) {
  out->set_scan(scan);
  for (const flows::SourceConfidence& c : cameras) {
    v1::CameraConfidence* cam = out->add_cameras();
    cam->set_source_id(c.source_id);
    cam->set_source(c.source);
    cam->set_width_px(c.width_px);
    cam->set_height_px(c.height_px);
    for (const flows::ArtefactMap& m : c.artefacts) {
      v1::ArtefactCoverage* a = cam->add_artefacts();
      a->set_artefact(m.artefact);
      a->set_covered_fraction(m.covered_fraction);
      a->set_flagged_pixels(m.flagged_pixels);
      a->set_soft_pixels(m.soft_pixels);
      a->set_regions(m.regions);
      a->set_max_extent_px(m.max_extent_px);
      a->set_map_size_bytes(int64_t(m.png.size()));
      for (double o : m.channel_offsets_px) a->add_channel_offsets_px(o);
      a->set_jpeg_quality(m.jpeg_quality);
      a->set_lens_map(m.lens_map);
      a->set_smear_offset(m.smear_offset);
      a->set_chroma_subsampled(m.chroma_subsampled);
    }
  }
}

render::ImageFormat ImageFormatFromProto(v1::ImageFormat format) {
  switch (format) {
    case v1::IMAGE_FORMAT_PNG:
      return render::ImageFormat::kPng;
    case v1::IMAGE_FORMAT_DEEP_EXR:
      return render::ImageFormat::kDeepExr;
    default:
      return render::ImageFormat::kExr;
  }
}

void VersionToProto(const store::VersionInfo& info, v1::Version* out) {
  out->set_version(info.version);
  out->set_vossel_count(info.vossel_count);
  out->set_record_count(info.record_count);
  out->set_tile_count(info.tile_count);
  out->set_bytes_written(info.bytes_written);
  out->set_bytes_total(info.bytes_total);
  out->set_made_by(info.made_by);
  out->set_pinned(info.pinned);
  TimestampFromIso(info.created_utc, out->mutable_commit_time());
}

void ChangeStatsToProto(const IngestResult& result, v1::ChangeStats* out) {
  out->set_sources_computed(result.sources_computed);
  out->set_sources_revisited(result.sources_revisited);
  out->set_pairs_revisited(result.pairs_revisited);
  out->set_blocks_revisited(result.blocks_revisited);
  out->set_sources_refreshed(result.sources_refreshed);
  out->set_vossels_revisited(result.vossels_revisited);
  out->set_tiles_changed(result.tiles_changed);
  out->set_bytes_written(result.bytes_written);
}

void StagesToProto(const std::vector<std::pair<std::string, double>>& stages,
                   google::protobuf::RepeatedPtrField<v1::StageTime>* out) {
  for (const auto& [stage, seconds] : stages) {
    v1::StageTime* t = out->Add();
    t->set_stage(stage);
    t->set_seconds(seconds);
  }
}

void ChangeToProto(const IngestResult& result, v1::ChangeResponse* out) {
  out->set_version(result.version);
  out->set_vossel_count(result.vossel_count);
  out->set_record_count(result.record_count);
  out->set_seconds(result.seconds);
  StagesToProto(result.stage_seconds, out->mutable_stages());
  ChangeStatsToProto(result, out->mutable_change());
}

}  // namespace vasl::server

/// @file vasl_service.cc
/// @brief vasl.v1.VaslService over the lattice Engine (callback API, worker pool).
#include "server/vasl_service.h"

#include <cstdio>
#include <ctime>
#include <memory>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "lattice/render/encode.h"
#include "server/convert.h"
#include "server/ingest_assembler.h"
#include "server/status_util.h"

namespace vasl::server {
namespace {

using Clock = std::chrono::steady_clock;

double SecondsSince(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

grpc::Status Unavailable() {
  return grpc::Status(grpc::StatusCode::UNAVAILABLE, "the server is shutting down; retry later");
}

/// DEADLINE_EXCEEDED or CANCELLED if the client gave up before the work starts.
bool ClientGone(grpc::CallbackServerContext* context, grpc::Status* status) {
  if (context->deadline() < std::chrono::system_clock::now()) {
    *status = grpc::Status(grpc::StatusCode::DEADLINE_EXCEEDED,
                           "the deadline passed before the request could start");
    return true;
  }
  return false;
}

// ---------------------------------------------------------------------------------------------
// IngestScan: one reader reactor per stream. Reads and assembles on gRPC's threads (cheap
// appends), runs the engine on the pool, finishes from there.
class IngestReactor final : public grpc::ServerReadReactor<v1::IngestScanRequest> {
 public:
  IngestReactor(VaslServiceImpl* service, grpc::CallbackServerContext* context,
                v1::IngestScanResponse* response)
      : service_(service),
        context_(context),
        response_(response),
        assembler_(service->engine()->limits()),
        start_(Clock::now()) {
    StartRead(&request_);
  }

  void OnReadDone(bool ok) override {
    if (!ok) {
      EndOfStream();
      return;
    }
    const bool was_header = !assembler_.has_header();
    absl::Status status = assembler_.Add(request_);
    if (!status.ok()) {
      Fail(status);
      return;
    }
    if (was_header) {
      service_->UpdateProgress(assembler_.project(), [&](v1::IngestProgress& p) {
        p = v1::IngestProgress();
        p.set_state(v1::IngestProgress::STATE_RECEIVING);
        p.set_project(assembler_.project());
        p.set_scan(assembler_.scan_name());
        p.set_stage("upload");
      });
    } else if (++reads_since_progress_ >= 8) {
      reads_since_progress_ = 0;
      const int64_t bytes = assembler_.received_bytes();
      const double elapsed = SecondsSince(start_);
      service_->UpdateProgress(assembler_.project(), [&](v1::IngestProgress& p) {
        p.set_received_bytes(bytes);
        p.set_elapsed_s(elapsed);
      });
    }
    request_.Clear();
    StartRead(&request_);
  }

  void OnDone() override { delete this; }

 private:
  void EndOfStream() {
    if (context_->IsCancelled()) {
      Finish(grpc::Status(grpc::StatusCode::CANCELLED, "the client cancelled the ingest"), false);
      return;
    }
    absl::StatusOr<ScanInput> scan = assembler_.Finish();
    if (!scan.ok()) {
      Fail(scan.status());
      return;
    }
    auto input = std::make_shared<ScanInput>(std::move(*scan));
    const bool queued = service_->pool()->Submit([this, input] { Run(*input); });
    if (!queued) Finish(Unavailable(), true);
  }

  void Run(const ScanInput& scan) {
    const std::string project = assembler_.project();
    const int64_t received = assembler_.received_bytes();
    service_->UpdateProgress(project, [&](v1::IngestProgress& p) {
      p.set_state(v1::IngestProgress::STATE_PROCESSING);
      p.set_stage("queued");
      p.set_received_bytes(received);
      p.set_elapsed_s(SecondsSince(start_));
    });
    std::mutex stage_mutex;  // the engine may report from several threads
    std::string last_stage;
    ProgressFn progress = [&](const Progress& step) {
      const double elapsed = SecondsSince(start_);
      std::lock_guard<std::mutex> lock(stage_mutex);
      service_->UpdateProgress(project, [&](v1::IngestProgress& p) {
        p.set_stage(step.stage);
        p.set_fraction(step.fraction);
        p.set_elapsed_s(elapsed);
      });
      if (step.stage != last_stage) {
        last_stage = step.stage;
        service_->options().log(absl::StrFormat(
            "IngestScan progress project=%s scan=%s stage=%s fraction=%.2f elapsed_s=%.1f",
            project, scan.scan_name, step.stage, step.fraction, elapsed));
      }
    };
    absl::StatusOr<IngestResult> result =
        service_->engine()->IngestScan(project, scan, progress);
    if (!result.ok()) {
      Fail(result.status());
      return;
    }
    response_->set_scan_id(result->scan_id);
    response_->set_scan(scan.scan_name);
    response_->set_version(result->version);
    response_->set_vossel_count(result->vossel_count);
    response_->set_record_count(result->record_count);
    response_->set_new_vossels(result->new_vossels);
    response_->set_point_count(static_cast<int64_t>(scan.lidar.xyz_sensor_m.size() / 3));
    response_->set_ingest_seconds(result->seconds);
    response_->set_total_seconds(SecondsSince(start_));
    for (const auto& [stage, seconds] : result->stage_seconds) {
      v1::StageTime* t = response_->add_stages();
      t->set_stage(stage);
      t->set_seconds(seconds);
    }
    Finish(grpc::Status::OK, true);
  }

  void Fail(const absl::Status& status) { Finish(ToGrpcStatus(status), assembler_.has_header()); }

  void Finish(const grpc::Status& status, bool track) {
    const std::string& project = assembler_.project();
    if (track && !project.empty()) {
      const double elapsed = SecondsSince(start_);
      service_->UpdateProgress(project, [&](v1::IngestProgress& p) {
        p.set_state(status.ok() ? v1::IngestProgress::STATE_SUCCEEDED
                                : v1::IngestProgress::STATE_FAILED);
        if (status.ok()) p.set_fraction(1.0);
        p.set_stage(status.ok() ? "done" : p.stage());
        p.set_message(status.error_message());
        p.set_elapsed_s(elapsed);
      });
    }
    service_->LogRequest("IngestScan", project, status, start_);
    grpc::ServerReadReactor<v1::IngestScanRequest>::Finish(status);
  }

  VaslServiceImpl* service_;
  grpc::CallbackServerContext* context_;
  v1::IngestScanResponse* response_;
  IngestAssembler assembler_;
  v1::IngestScanRequest request_;
  Clock::time_point start_;
  int reads_since_progress_ = 0;
};

// ---------------------------------------------------------------------------------------------
// Render: one writer reactor per call. Renders and encodes on the pool, then streams the
// metadata and each format's bytes in chunks; each write is started from the previous write's
// completion.
class RenderReactor final : public grpc::ServerWriteReactor<v1::RenderResponse> {
 public:
  RenderReactor(VaslServiceImpl* service, grpc::CallbackServerContext* context,
                const v1::RenderRequest* request)
      : service_(service), context_(context), request_(*request), start_(Clock::now()) {
    const bool queued = service_->pool()->Submit([this] { Run(); });
    if (!queued) Done(Unavailable());
  }

  void OnWriteDone(bool ok) override {
    if (!ok) {
      Done(grpc::Status(grpc::StatusCode::CANCELLED, "the client stopped reading the render"));
      return;
    }
    WriteNext();
  }

  void OnDone() override { delete this; }

 private:
  void Run() {
    grpc::Status gone;
    if (ClientGone(context_, &gone)) {
      Done(gone);
      return;
    }
    const EngineLimits& limits = service_->engine()->limits();
    absl::StatusOr<render::RenderRequest> request = RenderRequestFromProto(request_, limits);
    if (!request.ok()) return Done(ToGrpcStatus(request.status()));
    absl::StatusOr<std::vector<v1::ImageFormat>> formats = RenderFormatsFromProto(request_);
    if (!formats.ok()) return Done(ToGrpcStatus(formats.status()));
    if (request_.project().empty()) {
      return Done(grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "project is empty"));
    }
    const Clock::time_point render_start = Clock::now();
    absl::StatusOr<RenderImage> image = service_->engine()->Render(request_.project(), *request);
    if (!image.ok()) return Done(ToGrpcStatus(image.status()));
    const double render_seconds = SecondsSince(render_start);
    const Clock::time_point encode_start = Clock::now();
    v1::RenderMetadata* meta = first_.mutable_metadata();
    for (v1::ImageFormat format : *formats) {
      absl::StatusOr<std::string> bytes = format == v1::IMAGE_FORMAT_EXR
                                              ? render::EncodeExr(*image)
                                              : render::EncodePng(*image);
      if (!bytes.ok()) return Done(ToGrpcStatus(bytes.status()));
      meta->add_formats(format);
      meta->add_size_bytes(static_cast<int64_t>(bytes->size()));
      encoded_.emplace_back(format, std::move(*bytes));
    }
    meta->set_width_px(image->width_px);
    meta->set_height_px(image->height_px);
    meta->set_version(image->version);
    meta->set_hit_pixels(image->hit_pixels);
    meta->set_render_seconds(render_seconds);
    meta->set_encode_seconds(SecondsSince(encode_start));
    StartWrite(&first_);
  }

  void WriteNext() {
    const size_t chunk = static_cast<size_t>(service_->options().render_chunk_bytes);
    while (format_index_ < encoded_.size() && offset_ >= encoded_[format_index_].second.size()) {
      ++format_index_;
      offset_ = 0;
    }
    if (format_index_ >= encoded_.size()) {
      Done(grpc::Status::OK);
      return;
    }
    const auto& [format, bytes] = encoded_[format_index_];
    const size_t n = std::min(chunk, bytes.size() - offset_);
    chunk_.Clear();
    v1::RenderChunk* c = chunk_.mutable_chunk();
    c->set_format(format);
    c->set_offset_bytes(static_cast<int64_t>(offset_));
    c->set_data(bytes.data() + offset_, n);
    offset_ += n;
    StartWrite(&chunk_);
  }

  void Done(const grpc::Status& status) {
    service_->LogRequest("Render", request_.project(), status, start_);
    Finish(status);
  }

  VaslServiceImpl* service_;
  grpc::CallbackServerContext* context_;
  v1::RenderRequest request_;
  Clock::time_point start_;
  v1::RenderResponse first_;
  v1::RenderResponse chunk_;
  std::vector<std::pair<v1::ImageFormat, std::string>> encoded_;
  size_t format_index_ = 0;
  size_t offset_ = 0;
};

}  // namespace

void StderrLogSink(const std::string& line) {
  const std::time_t now = std::time(nullptr);
  std::tm tm_utc{};
  gmtime_r(&now, &tm_utc);
  char stamp[32];
  std::strftime(stamp, sizeof(stamp), "%Y-%m-%dT%H:%M:%SZ", &tm_utc);
  std::fprintf(stderr, "%s vasld %s\n", stamp, line.c_str());
  std::fflush(stderr);
}

VaslServiceImpl::VaslServiceImpl(Engine* engine, WorkerPool* pool, ServiceOptions options)
    : engine_(engine), pool_(pool), options_(std::move(options)) {
  if (!options_.log) options_.log = StderrLogSink;
}

void VaslServiceImpl::LogRequest(const char* method, const std::string& project,
                                 const grpc::Status& status, Clock::time_point start) const {
  const double ms = 1e3 * SecondsSince(start);
  std::string line = absl::StrFormat("%s project=%s code=%s ms=%.1f", method,
                                     project.empty() ? "-" : project,
                                     GrpcCodeName(status.error_code()), ms);
  if (!status.ok()) absl::StrAppend(&line, " message=\"", status.error_message(), "\"");
  options_.log(line);
}

void VaslServiceImpl::UpdateProgress(const std::string& project,
                                     const std::function<void(v1::IngestProgress&)>& update) {
  std::lock_guard<std::mutex> lock(progress_mutex_);
  v1::IngestProgress& p = progress_[project];
  update(p);
  p.set_project(project);
}

v1::IngestProgress VaslServiceImpl::GetProgress(const std::string& project) {
  std::lock_guard<std::mutex> lock(progress_mutex_);
  auto it = progress_.find(project);
  if (it != progress_.end()) return it->second;
  v1::IngestProgress idle;
  idle.set_state(v1::IngestProgress::STATE_IDLE);
  idle.set_project(project);
  return idle;
}

grpc::ServerUnaryReactor* VaslServiceImpl::RunUnary(grpc::CallbackServerContext* context,
                                                    const char* method,
                                                    const std::string& project,
                                                    std::function<grpc::Status()> body) {
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  const Clock::time_point start = Clock::now();
  const bool queued = pool_->Submit([this, context, reactor, method, project, start,
                                     body = std::move(body)] {
    grpc::Status status;
    if (!ClientGone(context, &status)) status = body();
    LogRequest(method, project, status, start);
    reactor->Finish(status);
  });
  if (!queued) {
    LogRequest(method, project, Unavailable(), start);
    reactor->Finish(Unavailable());
  }
  return reactor;
}

grpc::ServerUnaryReactor* VaslServiceImpl::CreateProject(grpc::CallbackServerContext* context,
                                                         const v1::CreateProjectRequest* request,
                                                         v1::Project* response) {
  return RunUnary(context, "CreateProject", request->name(), [this, request, response] {
    absl::StatusOr<store::ProjectSettings> settings = SettingsFromProto(*request);
    if (!settings.ok()) return ToGrpcStatus(settings.status());
    absl::StatusOr<ProjectInfo> info = engine_->CreateProject(request->name(), *settings);
    if (!info.ok()) return ToGrpcStatus(info.status());
    ProjectToProto(*info, response);
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* VaslServiceImpl::GetProject(grpc::CallbackServerContext* context,
                                                      const v1::GetProjectRequest* request,
                                                      v1::Project* response) {
  return RunUnary(context, "GetProject", request->project(), [this, request, response] {
    absl::StatusOr<ProjectInfo> info = engine_->GetProject(request->project());
    if (!info.ok()) return ToGrpcStatus(info.status());
    ProjectToProto(*info, response);
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* VaslServiceImpl::ListProjects(grpc::CallbackServerContext* context,
                                                        const v1::ListProjectsRequest* /*request*/,
                                                        v1::ListProjectsResponse* response) {
  return RunUnary(context, "ListProjects", "", [this, response] {
    absl::StatusOr<std::vector<ProjectInfo>> infos = engine_->ListProjects();
    if (!infos.ok()) return ToGrpcStatus(infos.status());
    for (const ProjectInfo& info : *infos) ProjectToProto(info, response->add_projects());
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* VaslServiceImpl::ListScans(grpc::CallbackServerContext* context,
                                                     const v1::ListScansRequest* request,
                                                     v1::ListScansResponse* response) {
  return RunUnary(context, "ListScans", request->project(), [this, request, response] {
    absl::StatusOr<std::vector<store::ScanInfo>> scans = engine_->ListScans(request->project());
    if (!scans.ok()) return ToGrpcStatus(scans.status());
    for (const store::ScanInfo& scan : *scans) ScanToProto(scan, response->add_scans());
    return grpc::Status::OK;
  });
}

grpc::ServerReadReactor<v1::IngestScanRequest>* VaslServiceImpl::IngestScan(
    grpc::CallbackServerContext* context, v1::IngestScanResponse* response) {
  return new IngestReactor(this, context, response);
}

grpc::ServerUnaryReactor* VaslServiceImpl::GetIngestProgress(
    grpc::CallbackServerContext* context, const v1::GetIngestProgressRequest* request,
    v1::IngestProgress* response) {
  v1::IngestProgress known = GetProgress(request->project());
  if (known.state() != v1::IngestProgress::STATE_IDLE) {
    // A map lookup: answered on the callback thread, so polls never wait behind engine work.
    const Clock::time_point start = Clock::now();
    *response = std::move(known);
    grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
    LogRequest("GetIngestProgress", request->project(), grpc::Status::OK, start);
    reactor->Finish(grpc::Status::OK);
    return reactor;
  }
  // Unknown so far: the engine tells NOT_FOUND from a project that has not ingested yet.
  return RunUnary(context, "GetIngestProgress", request->project(), [this, request, response] {
    v1::IngestProgress progress = GetProgress(request->project());
    if (progress.state() == v1::IngestProgress::STATE_IDLE) {
      absl::StatusOr<ProjectInfo> info = engine_->GetProject(request->project());
      if (!info.ok()) return ToGrpcStatus(info.status());
    }
    *response = std::move(progress);
    return grpc::Status::OK;
  });
}

grpc::ServerWriteReactor<v1::RenderResponse>* VaslServiceImpl::Render(
    grpc::CallbackServerContext* context, const v1::RenderRequest* request) {
  return new RenderReactor(this, context, request);
}

grpc::ServerUnaryReactor* VaslServiceImpl::InspectRecords(
    grpc::CallbackServerContext* context, const v1::InspectRecordsRequest* request,
    v1::InspectRecordsResponse* response) {
  return RunUnary(context, "InspectRecords", request->project(), [this, request, response] {
    if (request->version() < 0) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                          absl::StrCat("version must be >= 0 (0: HEAD), got ",
                                       request->version()));
    }
    absl::StatusOr<RecordsInspection> inspection =
        engine_->InspectRecords(request->project(), request->version());
    if (!inspection.ok()) return ToGrpcStatus(inspection.status());
    response->set_project(request->project());
    response->set_version(inspection->version);
    response->set_tile_count(inspection->tile_count);
    response->set_record_count(inspection->record_count);
    const std::vector<records::AttributeInfo>* attributes = &inspection->attributes;
    for (const records::AttributeInfo& a : *attributes) {
      AttributeToProto(a, response->add_attributes());
    }
    return grpc::Status::OK;
  });
}

}  // namespace vasl::server

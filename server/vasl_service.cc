/// @file vasl_service.cc
/// @brief vasl.v1.VaslService over the lattice Engine (callback API, worker pool).
#include "server/vasl_service.h"

#include <algorithm>

#include <unistd.h>

#include <atomic>
#include <condition_variable>
#include <cstdio>
#include <ctime>
#include <deque>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <memory>
#include <mutex>
#include <string_view>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "lattice/operations.h"
#include "lattice/render/encode.h"
#include "server/convert.h"
#include "server/paging.h"
#include "server/request_check.h"
#include "server/ingest_assembler.h"
#include "server/status_util.h"

namespace vasl::server {
namespace {

using Clock = std::chrono::steady_clock;

double SecondsSince(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

/// Client text as it may appear in a log line: printable ASCII, with quotes, backslashes,
/// control and non-ASCII bytes escaped (no forged lines), and at most `max` bytes of it.
std::string Printable(absl::string_view text, size_t max = 160) {
  std::string out;
  for (size_t i = 0; i < text.size() && i < max; ++i) {
    const unsigned char c = static_cast<unsigned char>(text[i]);
    if (c == '"' || c == '\\') {
      out += '\\';
      out += static_cast<char>(c);
    } else if (c < 0x20 || c >= 0x7f) {
      absl::StrAppendFormat(&out, "\\x%02x", c);
    } else {
      out += static_cast<char>(c);
    }
  }
  if (text.size() > max) absl::StrAppend(&out, "...(", text.size() - max, " more bytes)");
  return out;
}

/// The peer's address without its port ("ipv4:127.0.0.1:5312" -> "ipv4:127.0.0.1").
std::string PeerHost(const std::string& peer) {
  if (peer.rfind("ipv4:", 0) != 0 && peer.rfind("ipv6:", 0) != 0) return peer;
  const size_t colon = peer.rfind(':');
  return colon == std::string::npos || colon < 5 ? peer : peer.substr(0, colon);
}

/// DEADLINE_EXCEEDED if the client's deadline passed before the work starts.
bool ClientGone(grpc::CallbackServerContext* context, grpc::Status* status) {
  if (context->deadline() < std::chrono::system_clock::now()) {
    *status = grpc::Status(grpc::StatusCode::DEADLINE_EXCEEDED,
                           "the deadline passed before the request could start");
    return true;
  }
  return false;
}

}  // namespace

absl::Status StillWanted(grpc::CallbackServerContext* context) {
  if (context == nullptr) return absl::OkStatus();
  if (context->deadline() < std::chrono::system_clock::now()) {
    return absl::DeadlineExceededError(
        "the deadline passed while the work ran: it was stopped and nothing was committed");
  }
  if (context->IsCancelled()) {
    return absl::CancelledError(
        "the client cancelled the call: its work was stopped and nothing was committed");
  }
  return absl::OkStatus();
}

namespace {

// ---------------------------------------------------------------------------------------------
// BackProject: a header, then the image's bytes; the engine runs on the pool.
class BackProjectReactor final : public grpc::ServerReadReactor<v1::BackProjectRequest> {
 public:
  BackProjectReactor(VaslServiceImpl* service, grpc::CallbackServerContext* context,
                     v1::BackProjectResponse* response)
      : service_(service), context_(context), response_(response), start_(Clock::now()) {
    absl::StatusOr<Caller> caller = service_->Authorize(context, "", Role::kNone, "BackProject");
    if (!caller.ok()) {
      Finish(ToGrpcStatus(caller.status()));
      return;
    }
    caller_ = std::move(*caller);
    if (absl::Status busy = service_->AcquireSlot(context, &client_); !busy.ok()) {
      Finish(ToGrpcStatus(busy));
      return;
    }
    has_slot_ = true;
    StartRead(&request_);
  }

  void OnReadDone(bool ok) override {
    if (!ok) {
      EndOfStream();
      return;
    }
    if (absl::Status s = Add(); !s.ok()) {
      Finish(ToGrpcStatus(s));
      return;
    }
    if (committed_) {  // a retry of a back-projection that committed: answered now
      *response_ = ReplayedAnswer(*committed_, &v1::Operation::back_project);
      Finish(grpc::Status::OK);
      return;
    }
    request_.Clear();
    StartRead(&request_);
  }

  void OnDone() override {
    service_->HoldIngestBytes(-held_bytes_).IgnoreError();  // giving back cannot fail
    if (has_slot_) service_->ReleaseSlot(client_);
    delete this;
  }

 private:
  absl::Status Add() {
    if (absl::Status bad = CheckRequestStrings(request_); !bad.ok()) return bad;
    if (request_.has_header()) {
      if (has_header_) return absl::InvalidArgumentError("a back-projection stream has one header");
      const v1::BackProjectHeader& h = request_.header();
      has_header_ = true;
      project_ = h.project();
      if (absl::Status s = AccessControl::Require(caller_, project_, Role::kWrite, "BackProject");
          !s.ok()) {
        return s;
      }
      if (absl::Status full = service_->CheckDiskFloor(); !full.ok()) return full;
      if (absl::Status s = service_->StartOperation(project_, h.request_id(), "back-project",
                                                    h.name(), &committed_);
          !s.ok() || committed_) {
        return s;
      }
      request_id_ = input_.request_id = h.request_id();
      if (!h.has_pose()) return absl::InvalidArgumentError("header.pose is required");
      absl::StatusOr<geometry::Pose> pose = PoseFromProto(h.pose(), "header.pose");
      if (!pose.ok()) return pose.status();
      input_.pose = *pose;
      input_.name = h.name();
      input_.render_id = h.render_id();
      if (h.has_pinhole()) {
        input_.pinhole = true;
        absl::StatusOr<geometry::PinholeIntrinsics> k =
            PinholeFromProto(h.pinhole(), "header.pinhole");
        if (!k.ok()) return k.status();
        input_.intrinsics = *k;
      }
      const int64_t limit = service_->engine()->limits().max_image_bytes;
      if (h.image_size_bytes() <= 0 || h.image_size_bytes() > limit) {
        return h.image_size_bytes() <= 0
                   ? absl::InvalidArgumentError("header.image_size_bytes must be > 0")
                   : absl::ResourceExhaustedError(absl::StrCat(
                         "image of ", h.image_size_bytes(), " bytes exceeds the limit of ", limit));
      }
      expected_ = h.image_size_bytes();
      return absl::OkStatus();
    }
    if (!has_header_) return absl::InvalidArgumentError("the first message must be the header");
    if (int64_t(input_.image.size() + request_.image_chunk().size()) > expected_) {
      return absl::InvalidArgumentError(absl::StrCat(
          "more image bytes than header.image_size_bytes (", expected_, ")"));
    }
    if (absl::Status s = service_->HoldIngestBytes(int64_t(request_.image_chunk().size()));
        !s.ok()) {
      return s;
    }
    held_bytes_ += int64_t(request_.image_chunk().size());
    input_.image.append(request_.image_chunk());
    return absl::OkStatus();
  }

  void EndOfStream() {
    if (context_->IsCancelled()) {
      Finish(grpc::Status(grpc::StatusCode::CANCELLED, "the client cancelled the back-projection"));
      return;
    }
    if (!has_header_) {
      Finish(ToGrpcStatus(absl::InvalidArgumentError("the stream ended before its header")));
      return;
    }
    if (int64_t(input_.image.size()) != expected_) {
      Finish(ToGrpcStatus(absl::InvalidArgumentError(absl::StrCat(
          "the stream ended after ", input_.image.size(), " of ", expected_, " image bytes"))));
      return;
    }
    if (absl::Status s = service_->change_pool()->Submit([this] { Run(); }); !s.ok()) {
      Finish(ToGrpcStatus(s));
    }
  }

  void Run() {
    const ProgressFn progress = service_->ProgressReporter(
        context_, "BackProject", project_, "name=" + input_.name, start_, request_id_);
    const std::string name = input_.name;
    absl::StatusOr<IngestResult> r =
        service_->engine()->BackProject(project_, std::move(input_), progress);
    if (!r.ok()) {
      Finish(ToGrpcStatus(r.status()));
      return;
    }
    response_->set_request_id(request_id_);
    if (r->replayed) {  // it committed while this copy was uploading
      *response_ = ReplayedAnswer(
          OperationFromRecord(project_, {request_id_, "back-project", name, r->version,
                                         r->scan_id, r->answer}),
          &v1::Operation::back_project);
      replayed_ = true;
      Finish(grpc::Status::OK);
      return;
    }
    auto scans = service_->engine()->ListScans(project_);
    if (scans.ok() && !scans->empty()) response_->set_name(scans->back().name);
    response_->set_version(r->version);
    response_->set_pixels_back_projected(r->pixels_back_projected);
    response_->set_pixels_outside(r->pixels_outside);
    response_->set_pixels_invalid(r->pixels_invalid);
    response_->set_record_count(r->record_count);
    response_->set_seconds(r->seconds);
    ChangeStatsToProto(*r, response_->mutable_change());
    Finish(grpc::Status::OK);
  }

  void Finish(const grpc::Status& status) {
    if (!request_id_.empty()) {
      service_->EndOperation(project_, request_id_, status,
                             OperationWithAnswer(*response_, &v1::Operation::mutable_back_project),
                             !replayed_);
    }
    service_->LogRequest("BackProject", project_, status, start_);
    grpc::ServerReadReactor<v1::BackProjectRequest>::Finish(status);
  }

  VaslServiceImpl* service_;
  grpc::CallbackServerContext* context_;
  v1::BackProjectResponse* response_;
  v1::BackProjectRequest request_;
  BackProjectInput input_;
  std::string project_;
  bool has_header_ = false;
  int64_t expected_ = 0;
  int64_t held_bytes_ = 0;  // counted by HoldIngestBytes
  Caller caller_;           // authenticated when the stream opened
  std::string client_;
  bool has_slot_ = false;
  Clock::time_point start_;
  std::string request_id_;                  // set once StartOperation marked it running
  std::optional<v1::Operation> committed_;  // a retry of a committed back-projection
  bool replayed_ = false;                   // answered from a commit under request_id_
};

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
    // Who calls is known before any byte of the scan: a stranger's stream is refused at once.
    absl::StatusOr<Caller> caller = service_->Authorize(context, "", Role::kNone, "IngestScan");
    if (!caller.ok()) {
      Finish(ToGrpcStatus(caller.status()), false);
      return;
    }
    caller_ = std::move(*caller);
    if (absl::Status busy = service_->AcquireSlot(context, &client_); !busy.ok()) {
      Finish(ToGrpcStatus(busy), false);
      return;
    }
    has_slot_ = true;
    StartRead(&request_);
  }

  void OnReadDone(bool ok) override {
    if (!ok) {
      EndOfStream();
      return;
    }
    if (absl::Status bad = CheckRequestStrings(request_); !bad.ok()) {
      Finish(ToGrpcStatus(bad), assembler_.has_header());
      return;
    }
    const bool was_header = !assembler_.has_header();
    if (was_header && request_.has_header()) {
      if (absl::Status denied = AccessControl::Require(caller_, request_.header().project(),
                                                       Role::kWrite, "IngestScan");
          !denied.ok()) {
        Finish(ToGrpcStatus(denied), false);
        return;
      }
      if (absl::Status full = service_->CheckDiskFloor(); !full.ok()) {
        Finish(ToGrpcStatus(full), false);
        return;
      }
      const v1::ScanHeader& h = request_.header();
      std::optional<v1::Operation> committed;
      if (absl::Status s = service_->StartOperation(h.project(), h.request_id(), "ingest",
                                                    h.scan(), &committed);
          !s.ok()) {
        Finish(ToGrpcStatus(s), false);
        return;
      }
      if (committed) {  // a retry of an ingest that committed: answered now, nothing re-sent
        *response_ = ReplayedAnswer(*committed, &v1::Operation::ingest);
        Finish(grpc::Status::OK, false);
        return;
      }
      request_id_ = h.request_id();
    }
    absl::Status status = assembler_.Add(request_);
    if (status.ok()) {
      status = service_->HoldIngestBytes(assembler_.received_bytes() - held_bytes_);
      if (status.ok()) held_bytes_ = assembler_.received_bytes();
    }
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

  void OnDone() override {
    service_->HoldIngestBytes(-held_bytes_).IgnoreError();  // giving back cannot fail
    if (has_slot_) service_->ReleaseSlot(client_);
    delete this;
  }

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
    input->request_id = request_id_;
    absl::Status queued = service_->change_pool()->Submit([this, input] { Run(*input); });
    if (!queued.ok()) Finish(ToGrpcStatus(queued), true);
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
    const ProgressFn progress = service_->ProgressReporter(
        context_, "IngestScan", project, "scan=" + scan.scan_name, start_, request_id_);
    absl::StatusOr<IngestResult> result =
        service_->engine()->IngestScan(project, scan, progress);
    if (!result.ok()) {
      Fail(result.status());
      return;
    }
    response_->set_request_id(request_id_);
    if (result->replayed) {  // it committed while this copy was uploading
      *response_ = ReplayedAnswer(
          OperationFromRecord(project, {request_id_, "ingest", scan.scan_name, result->version,
                                        result->scan_id, result->answer}),
          &v1::Operation::ingest);
      replayed_ = true;
      Finish(grpc::Status::OK, true);
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
    StagesToProto(result->stage_seconds, response_->mutable_stages());
    ChangeStatsToProto(*result, response_->mutable_change());
    for (const auto& [camera, health] : result->calibration) {
      CalibrationToProto(camera, health, response_->add_calibration());
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
    if (!request_id_.empty()) {
      service_->EndOperation(project, request_id_, status,
                             OperationWithAnswer(*response_, &v1::Operation::mutable_ingest),
                             !replayed_);
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
  int64_t held_bytes_ = 0;  // counted by HoldIngestBytes
  Caller caller_;           // authenticated when the stream opened
  std::string client_;
  bool has_slot_ = false;
  std::string request_id_;  // set once StartOperation marked this ingest running
  bool replayed_ = false;   // answered from an ingest that committed under request_id_
};

// ---------------------------------------------------------------------------------------------
// Server streams of bytes (Render, Export, GetVisualReference): one writer reactor per call.
// `Produce` runs on the pool and hands each message to Send as soon as it is ready; the reactor
// writes them one at a time, each write started from the previous write's completion. Send
// waits while kQueuedBytes of messages wait for the client, so a slow reader holds the producer
// back instead of the server's memory. The call finishes only once Produce has returned (the
// reactor outlives its producer) and every message it sent was written.
template <typename Response>
class ChunkStreamReactor : public grpc::ServerWriteReactor<Response> {
 protected:
  grpc::CallbackServerContext* context() const { return context_; }

 public:
  ChunkStreamReactor(VaslServiceImpl* service, grpc::CallbackServerContext* context,
                     const char* method, std::string project)
      : service_(service), context_(context), method_(method), project_(std::move(project)),
        start_(Clock::now()) {}

  void OnWriteDone(bool ok) override {
    std::unique_lock<std::mutex> lock(mu_);
    writing_ = false;
    if (!ok) Break();
    WriteNext(lock);
  }

  void OnCancel() override {
    std::lock_guard<std::mutex> lock(mu_);
    Break();
  }

  void OnDone() override {
    if (has_slot_) service_->ReleaseSlot(client_);
    delete this;
  }

 protected:
  /// Messages not yet written that Send lets wait before it waits itself.
  static constexpr size_t kQueuedBytes = size_t{16} << 20;

  /// Checks the request's text fields and the caller's read role, then queues Run on the pool
  /// (call last in the derived constructor).
  void Start(const google::protobuf::Message& request) {
    if (absl::Status bad = CheckRequestStrings(request); !bad.ok()) return Done(ToGrpcStatus(bad));
    if (absl::StatusOr<Caller> caller =
            service_->Authorize(context_, project_, Role::kRead, method_);
        !caller.ok()) {
      return Done(ToGrpcStatus(caller.status()));
    }
    if (absl::Status busy = service_->AcquireSlot(context_, &client_); !busy.ok()) {
      return Done(ToGrpcStatus(busy));
    }
    has_slot_ = true;
    if (absl::Status s = service_->pool()->Submit([this] { Run(); }); !s.ok()) {
      Done(ToGrpcStatus(s));
    }
  }
  /// Sends the call's messages (Send, SendBytes) on the pool; its status ends the call (an
  /// error drops what was not yet written).
  virtual grpc::Status Produce() = 0;
  /// One chunk of payload `tag` at `offset`: every response's chunk carries its offset and
  /// bytes; a reactor whose payloads differ by tag overrides this to name it too.
  virtual void FillChunk(Response& out, int /*tag*/, int64_t offset, const char* data, size_t n) {
    auto* c = out.mutable_chunk();
    c->set_offset_bytes(offset);
    c->set_data(data, n);
  }

  /// Queues `message` for the client, waiting while kQueuedBytes wait. CANCELLED once the
  /// client stopped reading (the producer should stop).
  absl::Status Send(Response message) {
    std::unique_lock<std::mutex> lock(mu_);
    space_.wait(lock, [this] { return broken_ || queued_bytes_ < kQueuedBytes; });
    if (broken_) {
      return absl::CancelledError(absl::StrCat("the client stopped reading the ", method_,
                                               " stream"));
    }
    queued_bytes_ += message.ByteSizeLong();
    queue_.push_back(std::move(message));
    WriteNext(lock);
    return absl::OkStatus();
  }
  /// Sends `bytes`, payload `tag`'s bytes from `offset`, in chunks of the server's chunk size.
  absl::Status SendBytes(int tag, int64_t offset, std::string_view bytes) {
    const size_t chunk = static_cast<size_t>(service_->options().render_chunk_bytes);
    for (size_t at = 0; at < bytes.size(); at += chunk) {
      Response out;
      FillChunk(out, tag, offset + int64_t(at), bytes.data() + at,
                std::min(chunk, bytes.size() - at));
      if (absl::Status s = Send(std::move(out)); !s.ok()) return s;
    }
    return absl::OkStatus();
  }

  VaslServiceImpl* service_;

 private:
  void Run() {
    grpc::Status status;
    if (!ClientGone(context_, &status)) status = Produce();
    std::unique_lock<std::mutex> lock(mu_);
    produced_ = true;
    produced_status_ = status;
    if (!status.ok()) DropQueue();
    WriteNext(lock);
  }

  /// With mu_ held by `lock`: starts the next write, or finishes the call once the producer is
  /// done and nothing waits. Releases the lock when it writes or finishes.
  void WriteNext(std::unique_lock<std::mutex>& lock) {
    if (writing_ || finished_) return;
    if (!queue_.empty()) {
      current_ = std::move(queue_.front());
      queue_.pop_front();
      queued_bytes_ -= current_.ByteSizeLong();
      writing_ = true;
      space_.notify_all();
      lock.unlock();
      this->StartWrite(&current_);
      return;
    }
    if (!produced_) return;
    finished_ = true;
    grpc::Status status = produced_status_;
    if (broken_ && status.ok()) {
      status = grpc::Status(grpc::StatusCode::CANCELLED,
                            absl::StrCat("the client stopped reading the ", method_, " stream"));
    }
    lock.unlock();
    Done(status);
  }
  /// The client is gone: nothing more is written, and Send says so. With mu_ held.
  void Break() {
    broken_ = true;
    DropQueue();
    space_.notify_all();
  }
  void DropQueue() {
    queue_.clear();
    queued_bytes_ = 0;
  }

  void Done(const grpc::Status& status) {
    service_->LogRequest(method_, project_, status, start_);
    this->Finish(status);
  }

  grpc::CallbackServerContext* context_;
  const char* method_;
  std::string project_;
  Clock::time_point start_;
  std::string client_;
  bool has_slot_ = false;

  std::mutex mu_;
  std::condition_variable space_;  ///< signalled as the queue shrinks or the client goes
  std::deque<Response> queue_;     ///< sent, not yet written
  size_t queued_bytes_ = 0;
  Response current_;               ///< being written
  bool writing_ = false;
  bool broken_ = false;            ///< the client stopped reading or cancelled
  bool produced_ = false;          ///< Produce returned
  grpc::Status produced_status_;
  bool finished_ = false;
};

// Render: renders and encodes as bands of rows finish (render::RowEncoder per format). Streamed
// (stream_rows): each band's bytes go out as they are encoded, between a first and a last
// RenderMetadata; otherwise the files are gathered and sent after the metadata.
class RenderReactor final : public ChunkStreamReactor<v1::RenderResponse> {
 public:
  RenderReactor(VaslServiceImpl* service, grpc::CallbackServerContext* context,
                const v1::RenderRequest* request)
      : ChunkStreamReactor(service, context, "Render", request->project()), request_(*request) {
    Start(request_);
  }

 private:
  /// One requested format: its encoder, and its bytes when they are gathered.
  struct Output {
    v1::ImageFormat format;
    std::unique_ptr<render::RowEncoder> encoder;
    std::string bytes;
    int64_t size = 0;  ///< the file's size so far
  };

  grpc::Status Produce() override {
    const EngineLimits& limits = service_->engine()->limits();
    absl::StatusOr<render::RenderRequest> request = RenderRequestFromProto(request_, limits);
    if (!request.ok()) return ToGrpcStatus(request.status());
    absl::StatusOr<std::vector<v1::ImageFormat>> formats = RenderFormatsFromProto(request_);
    if (!formats.ok()) return ToGrpcStatus(formats.status());
    if (request_.project().empty()) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "project is empty");
    }
    const bool streamed = request_.stream_rows();
    if (streamed) {  // the size and formats first; the encoders' headers follow
      v1::RenderResponse first;
      first.mutable_metadata()->set_width_px(request->width_px);
      first.mutable_metadata()->set_height_px(request->height_px);
      for (v1::ImageFormat format : *formats) first.mutable_metadata()->add_formats(format);
      if (absl::Status s = Send(std::move(first)); !s.ok()) return ToGrpcStatus(s);
    }
    std::vector<Output> outputs(formats->size());
    for (size_t f = 0; f < outputs.size(); ++f) {
      Output& out = outputs[f];
      out.format = (*formats)[f];
      auto encoder = render::RowEncoder::Create(
          ImageFormatFromProto(out.format), request->width_px, request->height_px,
          [this, &out, streamed, gather = render::AssembleInto(&out.bytes)](
              int64_t offset, std::string_view run) {
            out.size = std::max(out.size, offset + int64_t(run.size()));
            return streamed ? SendBytes(out.format, offset, run) : gather(offset, run);
          });
      if (!encoder.ok()) return ToGrpcStatus(encoder.status());
      out.encoder = std::move(*encoder);
    }
    double encode_seconds = 0.0;
    const int rows_total = request->height_px;
    request->interrupt = [context = this->context()] { return StillWanted(context); };
    std::vector<render::RowEncoder*> encoders;
    for (Output& out : outputs) encoders.push_back(out.encoder.get());
    int rows_sent = 0;  // the last progress sent: rows whose bytes every format has sent
    request->rows_done = [&](const RenderImage& image, int row_begin, int row_end) {
      const Clock::time_point encode_start = Clock::now();
      if (absl::Status s = render::WriteRows(encoders, image, row_begin, row_end); !s.ok()) {
        return s;
      }
      encode_seconds += SecondsSince(encode_start);
      if (!streamed) return absl::OkStatus();
      int sent = row_end;
      for (const render::RowEncoder* e : encoders) sent = std::min(sent, e->rows_sent());
      if (sent <= rows_sent) return absl::OkStatus();  // no new rows reached the client
      rows_sent = sent;
      v1::RenderResponse progress;
      progress.mutable_progress()->set_rows_done(sent);
      progress.mutable_progress()->set_rows_total(rows_total);
      return Send(std::move(progress));
    };
    const Clock::time_point render_start = Clock::now();
    absl::StatusOr<RenderImage> image = service_->engine()->Render(request_.project(), *request);
    if (!image.ok()) return ToGrpcStatus(image.status());
    const Clock::time_point finish_start = Clock::now();
    for (Output& out : outputs) {
      if (absl::Status s = out.encoder->Finish(); !s.ok()) return ToGrpcStatus(s);
    }
    encode_seconds += SecondsSince(finish_start);
    v1::RenderResponse last;
    v1::RenderMetadata* meta = last.mutable_metadata();
    for (const Output& out : outputs) {
      meta->add_formats(out.format);
      meta->add_size_bytes(out.size);
    }
    meta->set_width_px(image->width_px);
    meta->set_height_px(image->height_px);
    meta->set_version(image->version);
    meta->set_hit_pixels(image->hit_pixels);
    meta->set_profile(image->profile);
    meta->set_profile_revision(image->profile_revision);
    meta->set_fused_on_the_fly(image->fused_on_the_fly);
    meta->set_render_id(image->render_id);
    meta->set_colourless_pixels(image->colourless_pixels);
    meta->set_detail_sources(image->detail_sources);
    meta->set_detail_sources_skipped(image->detail_sources_skipped);
    meta->set_tile_groups(image->tile_groups);
    meta->set_tiles_read(image->tiles_read);
    meta->set_tiles_total(image->tiles_total);
    meta->set_render_seconds(SecondsSince(render_start));
    meta->set_encode_seconds(encode_seconds);
    if (absl::Status s = Send(std::move(last)); !s.ok()) return ToGrpcStatus(s);
    if (streamed) return grpc::Status::OK;
    for (Output& out : outputs) {
      if (absl::Status s = SendBytes(out.format, 0, out.bytes); !s.ok()) return ToGrpcStatus(s);
      out.bytes = {};
    }
    return grpc::Status::OK;
  }

  void FillChunk(v1::RenderResponse& out, int tag, int64_t offset, const char* data,
                 size_t n) override {
    ChunkStreamReactor::FillChunk(out, tag, offset, data, n);
    out.mutable_chunk()->set_format(static_cast<v1::ImageFormat>(tag));
  }

  v1::RenderRequest request_;
};

// Export: writes the merged .vdb to a staging file, reads it back, streams it.
class ExportReactor final : public ChunkStreamReactor<v1::ExportResponse> {
 public:
  ExportReactor(VaslServiceImpl* service, grpc::CallbackServerContext* context,
                const v1::ExportRequest* request)
      : ChunkStreamReactor(service, context, "Export", request->project()), request_(*request) {
    Start(request_);
  }

 private:
  grpc::Status Produce() override {
    if (request_.version() < 0) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                          absl::StrCat("version must be >= 0 (0: HEAD), got ", request_.version()));
    }
    const std::filesystem::path staged = service_->ExportStagingPath();
    absl::StatusOr<flows::ExportResult> result =
        service_->engine()->Export(request_.project(), request_.version(), staged);
    std::string bytes;
    if (result.ok()) {
      std::ifstream in(staged, std::ios::binary);
      bytes.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
    }
    std::error_code ec;
    std::filesystem::remove(staged, ec);
    if (!result.ok()) return ToGrpcStatus(result.status());
    if (int64_t(bytes.size()) != result->size_bytes) {
      return grpc::Status(grpc::StatusCode::INTERNAL, "export: the staged file changed size");
    }
    v1::ExportResponse first;
    v1::ExportMetadata* meta = first.mutable_metadata();
    meta->set_version(result->version);
    meta->set_vossel_count(result->vossel_count);
    meta->set_record_count(result->record_count);
    meta->set_size_bytes(result->size_bytes);
    absl::Status sent = Send(std::move(first));
    if (sent.ok()) sent = SendBytes(0, 0, bytes);
    return ToGrpcStatus(sent);
  }

  v1::ExportRequest request_;
};

// GetVisualReference: a scan's reference photo, as it was sent.
class VisualReferenceReactor final : public ChunkStreamReactor<v1::GetVisualReferenceResponse> {
 public:
  VisualReferenceReactor(VaslServiceImpl* service, grpc::CallbackServerContext* context,
                         const v1::GetVisualReferenceRequest* request)
      : ChunkStreamReactor(service, context, "GetVisualReference", request->project()),
        request_(*request) {
    Start(request_);
  }

 private:
  grpc::Status Produce() override {
    auto found = service_->engine()->GetVisualReference(request_.project(), request_.scan(),
                                                        request_.name());
    if (!found.ok()) return ToGrpcStatus(found.status());
    v1::GetVisualReferenceResponse first;
    VisualReferenceToProto(found->first, first.mutable_reference());
    absl::Status sent = Send(std::move(first));
    if (sent.ok()) sent = SendBytes(0, 0, found->second);
    return ToGrpcStatus(sent);
  }

  v1::GetVisualReferenceRequest request_;
};

// GetConfidence: a scan's cameras' confidence maps (VASL-MODEL §9), the summary then the PNGs.
class ConfidenceReactor final : public ChunkStreamReactor<v1::GetConfidenceResponse> {
 public:
  ConfidenceReactor(VaslServiceImpl* service, grpc::CallbackServerContext* context,
                    const v1::GetConfidenceRequest* request)
      : ChunkStreamReactor(service, context, "GetConfidence", request->project()),
        request_(*request) {
    Start(request_);
  }

 private:
  static constexpr int kArtefacts = 1 << 8;  ///< tag = camera · kArtefacts + artefact

  grpc::Status Produce() override {
    auto found = service_->engine()->ScanConfidence(request_.project(), request_.scan());
    if (!found.ok()) return ToGrpcStatus(found.status());
    v1::GetConfidenceResponse first;
    ScanConfidenceToProto(request_.scan(), *found, first.mutable_summary());
    absl::Status sent = Send(std::move(first));
    for (size_t c = 0; c < found->size() && sent.ok(); ++c) {
      const std::vector<flows::ArtefactMap>& maps = (*found)[c].artefacts;
      for (size_t a = 0; a < maps.size() && sent.ok(); ++a) {
        sent = SendBytes(int(c) * kArtefacts + int(a), 0, maps[a].png);
      }
    }
    return ToGrpcStatus(sent);
  }

  void FillChunk(v1::GetConfidenceResponse& out, int tag, int64_t offset, const char* data,
                 size_t n) override {
    ChunkStreamReactor::FillChunk(out, tag, offset, data, n);
    out.mutable_chunk()->set_camera_index(tag / kArtefacts);
    out.mutable_chunk()->set_artefact_index(tag % kArtefacts);
  }

  v1::GetConfidenceRequest request_;
};

}  // namespace

std::filesystem::path VaslServiceImpl::ExportStagingPath() const {
  static std::atomic<uint64_t> counter{0};
  const std::filesystem::path dir = options_.staging_dir.empty()
                                        ? std::filesystem::temp_directory_path()
                                        : options_.staging_dir;
  return dir / absl::StrCat(".tmp-export-", ::getpid(), "-", counter.fetch_add(1));
}

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
  if (!options_.access) open_access_ = AccessControl::Open();
  access_ = options_.access ? options_.access : open_access_.get();
}

void VaslServiceImpl::LogRequest(const char* method, const std::string& project,
                                 const grpc::Status& status, Clock::time_point start) const {
  const double ms = 1e3 * SecondsSince(start);
  std::string line = absl::StrFormat("%s project=%s code=%s ms=%.1f", method,
                                     project.empty() ? "-" : Printable(project),
                                     GrpcCodeName(status.error_code()), ms);
  if (!status.ok()) {
    absl::StrAppend(&line, " message=\"", Printable(status.error_message(), 400), "\"");
  }
  options_.log(line);
}

void VaslServiceImpl::UpdateProgress(const std::string& project,
                                     const std::function<void(v1::IngestProgress&)>& update) {
  constexpr size_t kMaxBoard = 1024;  // projects whose last change is remembered
  std::lock_guard<std::mutex> lock(progress_mutex_);
  auto [it, added] = progress_.try_emplace(project);
  if (added) {
    progress_order_.push_back(project);
    // Forget the oldest finished entries beyond the bound (a running one is kept).
    for (size_t n = progress_order_.size(); progress_.size() > kMaxBoard && n > 0; --n) {
      const std::string oldest = progress_order_.front();
      progress_order_.pop_front();
      auto old = progress_.find(oldest);
      const auto state = old->second.state();
      if (oldest != project && state != v1::IngestProgress::STATE_RECEIVING &&
          state != v1::IngestProgress::STATE_PROCESSING) {
        progress_.erase(old);
      } else {
        progress_order_.push_back(oldest);
      }
    }
  }
  update(it->second);
  it->second.set_project(project);
}

absl::Status VaslServiceImpl::AcquireSlot(const grpc::CallbackServerContext* context,
                                          std::string* client) {
  *client = PeerHost(context->peer());
  if (options_.max_calls_per_client <= 0) return absl::OkStatus();
  std::lock_guard<std::mutex> lock(slots_mutex_);
  int& used = slots_[*client];
  if (used >= options_.max_calls_per_client) {
    if (used == 0) slots_.erase(*client);
    return absl::ResourceExhaustedError(absl::StrCat(
        "this client already has ", options_.max_calls_per_client,
        " calls running (limit --max-calls-per-client); wait for one to finish"));
  }
  ++used;
  return absl::OkStatus();
}

void VaslServiceImpl::ReleaseSlot(const std::string& client) {
  if (options_.max_calls_per_client <= 0) return;
  std::lock_guard<std::mutex> lock(slots_mutex_);
  auto it = slots_.find(client);
  if (it != slots_.end() && --it->second <= 0) slots_.erase(it);
}

absl::Status VaslServiceImpl::CheckDiskFloor() const {
  const int64_t floor = options_.min_free_disk_bytes;
  if (floor <= 0) return absl::OkStatus();
  std::error_code ec;
  const std::filesystem::space_info space = std::filesystem::space(options_.staging_dir, ec);
  if (ec || int64_t(space.available) >= floor) return absl::OkStatus();  // unknown: let it try
  return absl::ResourceExhaustedError(absl::StrCat(
      "the server's data disk has ", space.available >> 20, " MiB free, below the floor of ",
      floor >> 20, " MiB (--min-free-disk-bytes): nothing was written; retry once space is freed"));
}

absl::Status VaslServiceImpl::HoldIngestBytes(int64_t delta) {
  const int64_t limit = options_.max_inflight_ingest_bytes;
  const int64_t now = inflight_ingest_bytes_.fetch_add(delta) + delta;
  if (delta > 0 && limit > 0 && now > limit) {
    inflight_ingest_bytes_.fetch_sub(delta);
    return absl::ResourceExhaustedError(absl::StrCat(
        "the server already holds ", now - delta, " bytes of incoming scans (limit "
        "--max-inflight-ingest-bytes=", limit, "); retry when other uploads have finished"));
  }
  return absl::OkStatus();
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

ProgressFn VaslServiceImpl::ProgressReporter(grpc::CallbackServerContext* context,
                                             const char* method, const std::string& project,
                                             const std::string& what, Clock::time_point start,
                                             const std::string& request_id) {
  struct State {
    std::mutex mu;  // the engine may report from several threads
    std::string last_stage;
  };
  auto state = std::make_shared<State>();
  return [this, context, method, project, what, start, state,
          request_id](const Progress& step) {
    const double elapsed = SecondsSince(start);
    std::lock_guard<std::mutex> lock(state->mu);
    if (!request_id.empty()) operations_.Progress(project, request_id, step.stage, step.fraction);
    UpdateProgress(project, [&](v1::IngestProgress& p) {
      p.set_state(v1::IngestProgress::STATE_PROCESSING);
      p.set_stage(step.stage);
      p.set_fraction(step.fraction);
      p.set_elapsed_s(elapsed);
    });
    if (step.stage != state->last_stage) {
      state->last_stage = step.stage;
      options_.log(absl::StrFormat(
          "%s progress project=%s %s stage=%s fraction=%.2f elapsed_s=%.1f", method,
          Printable(project), Printable(what), step.stage, step.fraction, elapsed));
    }
    return StillWanted(context);
  };
}

absl::Status VaslServiceImpl::StartOperation(const std::string& project,
                                             const std::string& request_id,
                                             const std::string& kind, const std::string& subject,
                                             std::optional<v1::Operation>* committed) {
  committed->reset();
  if (request_id.empty()) return absl::OkStatus();
  absl::StatusOr<std::optional<store::OperationRecord>> done =
      engine_->FindOperation(project, store::OperationRecord{request_id, kind, subject});
  if (!done.ok()) return done.status();
  if (*done) {
    *committed = OperationFromRecord(project, **done);
    return absl::OkStatus();
  }
  return operations_.Begin(project, request_id, kind, subject);
}

void VaslServiceImpl::EndOperation(const std::string& project, const std::string& request_id,
                                   const grpc::Status& status, const v1::Operation& done,
                                   bool record) {
  if (request_id.empty()) return;
  if (!status.ok()) {
    operations_.Fail(project, request_id, status);
    return;
  }
  if (record) {
    // Best effort: the version is committed and recorded already; without the answer a retry
    // still learns it (OperationFromRecord).
    if (absl::Status s = engine_->SetOperationAnswer(project, request_id, done.SerializeAsString());
        !s.ok()) {
      options_.log(absl::StrCat("operation ", request_id, ": its answer was not recorded: ",
                                Printable(s.message())));
    }
  }
  operations_.Succeed(project, request_id, done);
}

absl::StatusOr<Caller> VaslServiceImpl::Authenticate(
    const grpc::CallbackServerContext* context) const {
  if (options_.require_client_certificate) {
    const std::shared_ptr<const grpc::AuthContext> auth = context->auth_context();
    if (auth == nullptr || !auth->IsPeerAuthenticated()) {
      return absl::UnauthenticatedError(
          "this server uses mutual TLS: present a client certificate signed by its client CA "
          "(only the health service answers without one)");
    }
  }
  const auto& metadata = context->client_metadata();
  auto it = metadata.find("authorization");
  const std::string header =
      it == metadata.end() ? std::string() : std::string(it->second.data(), it->second.size());
  return access_->Authenticate(header);
}

absl::StatusOr<Caller> VaslServiceImpl::Authorize(const grpc::CallbackServerContext* context,
                                                  const std::string& project, Role need,
                                                  const char* method) const {
  absl::StatusOr<Caller> caller = Authenticate(context);
  if (!caller.ok() || need == Role::kNone) return caller;
  if (absl::Status s = AccessControl::Require(*caller, project, need, method); !s.ok()) return s;
  return caller;
}

grpc::ServerUnaryReactor* VaslServiceImpl::Deny(grpc::CallbackServerContext* context,
                                                const char* method, const std::string& project,
                                                const grpc::Status& status) {
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  LogRequest(method, project, status, Clock::now());
  reactor->Finish(status);
  return reactor;
}

grpc::ServerUnaryReactor* VaslServiceImpl::RunOn(
    WorkerPool* lane, grpc::CallbackServerContext* context,
    const google::protobuf::Message& request, const char* method, const std::string& project, Role need,
    std::function<grpc::Status(const Caller&)> body) {
  if (absl::Status bad = CheckRequestStrings(request); !bad.ok()) {
    return Deny(context, method, "", ToGrpcStatus(bad));
  }
  absl::StatusOr<Caller> caller = Authorize(context, project, need, method);
  if (!caller.ok()) return Deny(context, method, project, ToGrpcStatus(caller.status()));
  if (need == Role::kWrite) {
    if (absl::Status full = CheckDiskFloor(); !full.ok()) {
      return Deny(context, method, project, ToGrpcStatus(full));
    }
  }
  std::string client;
  if (absl::Status busy = AcquireSlot(context, &client); !busy.ok()) {
    return Deny(context, method, project, ToGrpcStatus(busy));
  }
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  const Clock::time_point start = Clock::now();
  const absl::Status queued = lane->Submit([this, context, reactor, method, project, start,
                                            client, caller = std::move(*caller),
                                            body = std::move(body)] {
    grpc::Status status;
    try {
      if (!ClientGone(context, &status)) status = body(caller);
    } catch (const std::exception& e) {  // a bug or exhausted memory: answer, do not hang or die
      status = grpc::Status(grpc::StatusCode::INTERNAL,
                            std::string("unexpected error in the server: ") + e.what());
    } catch (...) {
      status = grpc::Status(grpc::StatusCode::INTERNAL, "unexpected error in the server");
    }
    LogRequest(method, project, status, start);
    ReleaseSlot(client);
    reactor->Finish(status);
  });
  if (!queued.ok()) {
    LogRequest(method, project, ToGrpcStatus(queued), start);
    ReleaseSlot(client);
    reactor->Finish(ToGrpcStatus(queued));
  }
  return reactor;
}

grpc::ServerUnaryReactor* VaslServiceImpl::CreateProject(grpc::CallbackServerContext* context,
                                                         const v1::CreateProjectRequest* request,
                                                         v1::Project* response) {
  // Authorised on every project ("*"), logged under the new project's name.
  return RunUnary(context, *request, "CreateProject", request->name(), Role::kNone,
                  [this, request, response](const Caller& caller) {
    if (absl::Status s = AccessControl::Require(caller, kAllProjects, Role::kWrite,
                                                "CreateProject");
        !s.ok()) {
      return ToGrpcStatus(s);
    }
    if (absl::Status full = CheckDiskFloor(); !full.ok()) return ToGrpcStatus(full);
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
  return RunUnary(context, *request, "GetProject", request->project(), Role::kRead,
                  [this, request, response] {
    absl::StatusOr<ProjectInfo> info = engine_->GetProject(request->project());
    if (!info.ok()) return ToGrpcStatus(info.status());
    ProjectToProto(*info, response);
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* VaslServiceImpl::ListProjects(grpc::CallbackServerContext* context,
                                                        const v1::ListProjectsRequest* request,
                                                        v1::ListProjectsResponse* response) {
  return RunUnary(context, *request, "ListProjects", "", Role::kNone,
                  [this, request, response](const Caller& caller) {
    absl::StatusOr<std::vector<ProjectInfo>> infos = engine_->ListProjects();
    if (!infos.ok()) return ToGrpcStatus(infos.status());
    // Only the projects the caller may read.
    infos->erase(std::remove_if(infos->begin(), infos->end(),
                                [&](const ProjectInfo& p) {
                                  return caller.RoleOn(p.name) < Role::kRead;
                                }),
                 infos->end());
    std::sort(infos->begin(), infos->end(),
              [](const ProjectInfo& a, const ProjectInfo& b) { return a.name < b.name; });
    auto page = Page(*infos, request->page_size(), request->page_token(),
                     [](const ProjectInfo& p) { return p.name; },
                     response->mutable_next_page_token());
    if (!page.ok()) return ToGrpcStatus(page.status());
    for (const ProjectInfo* info : *page) ProjectToProto(*info, response->add_projects());
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* VaslServiceImpl::ListScans(grpc::CallbackServerContext* context,
                                                     const v1::ListScansRequest* request,
                                                     v1::ListScansResponse* response) {
  return RunUnary(context, *request, "ListScans", request->project(), Role::kRead, [this, request, response] {
    absl::StatusOr<std::vector<store::ScanInfo>> scans = engine_->ListScans(request->project());
    if (!scans.ok()) return ToGrpcStatus(scans.status());
    auto page = Page(*scans, request->page_size(), request->page_token(),
                     [](const store::ScanInfo& s) { return IntKey(s.id); },
                     response->mutable_next_page_token());
    if (!page.ok()) return ToGrpcStatus(page.status());
    for (const store::ScanInfo* scan : *page) ScanToProto(*scan, response->add_scans());
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
  if (absl::Status bad = CheckRequestStrings(*request); !bad.ok()) {
    return Deny(context, "GetIngestProgress", "", ToGrpcStatus(bad));
  }
  if (absl::StatusOr<Caller> caller =
          Authorize(context, request->project(), Role::kRead, "GetIngestProgress");
      !caller.ok()) {
    return Deny(context, "GetIngestProgress", request->project(), ToGrpcStatus(caller.status()));
  }
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
  return RunUnary(context, *request, "GetIngestProgress", request->project(), Role::kRead,
                  [this, request, response] {
    v1::IngestProgress progress = GetProgress(request->project());
    if (progress.state() == v1::IngestProgress::STATE_IDLE) {
      absl::StatusOr<ProjectInfo> info = engine_->GetProject(request->project());
      if (!info.ok()) return ToGrpcStatus(info.status());
    }
    *response = std::move(progress);
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* VaslServiceImpl::GetOperation(grpc::CallbackServerContext* context,
                                                        const v1::GetOperationRequest* request,
                                                        v1::Operation* response) {
  return RunUnary(context, *request, "GetOperation", request->project(), Role::kRead,
                  [this, request, response] {
    const std::string& id = request->request_id();
    if (absl::Status bad = store::ValidateRequestId(id); !bad.ok()) return ToGrpcStatus(bad);
    // Memory first (running changes are only there); a failure seen there yields to a commit
    // in the catalog, which is the record of what happened.
    std::optional<v1::Operation> seen = operations_.Get(request->project(), id);
    if (seen && seen->state() != v1::Operation::STATE_FAILED) {
      *response = std::move(*seen);
      return grpc::Status::OK;
    }
    absl::StatusOr<std::optional<store::OperationRecord>> done =
        engine_->FindOperation(request->project(), store::OperationRecord{id, "", ""});
    if (!done.ok()) return ToGrpcStatus(done.status());
    if (!*done && seen) {
      *response = std::move(*seen);
      return grpc::Status::OK;
    }
    if (!*done) {
      return grpc::Status(grpc::StatusCode::NOT_FOUND,
                          absl::StrCat("project ", request->project(), " has no operation \"", id,
                                       "\": nothing committed under that id, and none running or "
                                       "failed since the server started; send the change again"));
    }
    *response = OperationFromRecord(request->project(), **done);
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
  return RunUnary(context, *request, "InspectRecords", request->project(), Role::kRead,
                  [this, request, response] {
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

grpc::ServerUnaryReactor* VaslServiceImpl::Rebuild(grpc::CallbackServerContext* context,
                                                   const v1::RebuildRequest* request,
                                                   v1::ChangeResponse* response) {
  return RunChangeUnary(context, *request, "Rebuild", request->project(), Role::kWrite,
                        [this, context, request, response] {
    return RunChange(context, request->project(), request->request_id(), "rebuild", "", response,
                     [&](const ProgressFn& progress) {
                       return engine_->Rebuild(request->project(), progress, request->request_id());
                     });
  });
}

grpc::ServerUnaryReactor* VaslServiceImpl::DeleteScan(grpc::CallbackServerContext* context,
                                                      const v1::DeleteScanRequest* request,
                                                      v1::ChangeResponse* response) {
  return RunChangeUnary(context, *request, "DeleteScan", request->project(), Role::kAdmin,
                        [this, context, request, response] {
    if (request->scan().empty()) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "scan is empty: name the scan to delete");
    }
    return RunChange(context, request->project(), request->request_id(), "delete",
                     request->scan(), response, [&](const ProgressFn& progress) {
                       return engine_->DeleteScan(request->project(), request->scan(), progress,
                                                  request->request_id());
                     });
  });
}

grpc::Status VaslServiceImpl::RunChange(
    grpc::CallbackServerContext* context, const std::string& project,
    const std::string& request_id, const std::string& kind, const std::string& subject, v1::ChangeResponse* response,
    const std::function<absl::StatusOr<IngestResult>(const ProgressFn&)>& change) {
  std::optional<v1::Operation> committed;
  if (absl::Status s = StartOperation(project, request_id, kind, subject, &committed); !s.ok()) {
    return ToGrpcStatus(s);
  }
  if (committed) {
    *response = ReplayedAnswer(*committed, &v1::Operation::change);
    return grpc::Status::OK;
  }
  const std::string what = subject.empty() ? kind : absl::StrCat(kind, "=", subject);
  const ProgressFn progress =
      ProgressReporter(context, kind == "rebuild" ? "Rebuild" : "DeleteScan", project, what,
                       Clock::now(), request_id);
  const absl::StatusOr<IngestResult> result = change(progress);
  grpc::Status status = FinishChange(project, result, response);
  response->set_request_id(request_id);
  const bool replayed = result.ok() && result->replayed;
  if (replayed) {
    *response = ReplayedAnswer(OperationFromRecord(project, {request_id, kind, subject,
                                                             result->version, result->scan_id,
                                                             result->answer}),
                               &v1::Operation::change);
  }
  EndOperation(project, request_id, status,
               OperationWithAnswer(*response, &v1::Operation::mutable_change), !replayed);
  return status;
}

grpc::Status VaslServiceImpl::FinishChange(const std::string& project,
                                           const absl::StatusOr<IngestResult>& result,
                                           v1::ChangeResponse* response) {
  UpdateProgress(project, [&](v1::IngestProgress& p) {
    p.set_state(result.ok() ? v1::IngestProgress::STATE_SUCCEEDED : v1::IngestProgress::STATE_FAILED);
    p.set_fraction(result.ok() ? 1.0 : p.fraction());
    p.set_message(result.ok() ? "" : std::string(result.status().message()));
  });
  if (!result.ok()) return ToGrpcStatus(result.status());
  ChangeToProto(*result, response);
  return grpc::Status::OK;
}

grpc::ServerUnaryReactor* VaslServiceImpl::ListVersions(grpc::CallbackServerContext* context,
                                                        const v1::ListVersionsRequest* request,
                                                        v1::ListVersionsResponse* response) {
  return RunUnary(context, *request, "ListVersions", request->project(), Role::kRead,
                  [this, request, response] {
    absl::StatusOr<std::vector<store::VersionInfo>> versions = engine_->ListVersions(request->project());
    if (!versions.ok()) return ToGrpcStatus(versions.status());
    auto page = Page(*versions, request->page_size(), request->page_token(),
                     [](const store::VersionInfo& v) { return IntKey(v.version); },
                     response->mutable_next_page_token());
    if (!page.ok()) return ToGrpcStatus(page.status());
    for (const store::VersionInfo* v : *page) VersionToProto(*v, response->add_versions());
    return grpc::Status::OK;
  });
}

grpc::ServerWriteReactor<v1::GetConfidenceResponse>* VaslServiceImpl::GetConfidence(
    grpc::CallbackServerContext* context, const v1::GetConfidenceRequest* request) {
  return new ConfidenceReactor(this, context, request);
}

grpc::ServerWriteReactor<v1::GetVisualReferenceResponse>* VaslServiceImpl::GetVisualReference(
    grpc::CallbackServerContext* context, const v1::GetVisualReferenceRequest* request) {
  return new VisualReferenceReactor(this, context, request);
}

grpc::ServerWriteReactor<v1::ExportResponse>* VaslServiceImpl::Export(
    grpc::CallbackServerContext* context, const v1::ExportRequest* request) {
  return new ExportReactor(this, context, request);
}

grpc::ServerUnaryReactor* VaslServiceImpl::CreateProfile(grpc::CallbackServerContext* context,
                                                         const v1::CreateProfileRequest* request,
                                                         v1::WeightingProfile* response) {
  return RunUnary(context, *request, "CreateProfile", request->project(), Role::kWrite,
                  [this, request, response] {
    if (!request->has_profile()) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "profile is required");
    }
    absl::StatusOr<fusion::WeightingProfile> profile = ProfileFromProto(request->profile());
    if (!profile.ok()) return ToGrpcStatus(profile.status());
    absl::StatusOr<reweight::NamedProfile> made = engine_->CreateProfile(request->project(), *profile);
    if (!made.ok()) return ToGrpcStatus(made.status());
    if (request->activate()) {
      absl::Status s = engine_->SetActiveProfile(request->project(), made->profile.name);
      if (!s.ok()) return ToGrpcStatus(s);
    }
    ProfileToProto(made->profile, made->created_utc, response);
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* VaslServiceImpl::GetProfile(grpc::CallbackServerContext* context,
                                                      const v1::GetProfileRequest* request,
                                                      v1::WeightingProfile* response) {
  return RunUnary(context, *request, "GetProfile", request->project(), Role::kRead,
                  [this, request, response] {
    absl::StatusOr<reweight::NamedProfile> p =
        engine_->GetProfile(request->project(), request->name(), request->revision());
    if (!p.ok()) return ToGrpcStatus(p.status());
    ProfileToProto(p->profile, p->created_utc, response);
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* VaslServiceImpl::ListProfiles(grpc::CallbackServerContext* context,
                                                        const v1::ListProfilesRequest* request,
                                                        v1::ListProfilesResponse* response) {
  return RunUnary(context, *request, "ListProfiles", request->project(), Role::kRead,
                  [this, request, response] {
    std::string active;
    absl::StatusOr<std::vector<reweight::NamedProfile>> all =
        engine_->ListProfiles(request->project(), &active);
    if (!all.ok()) return ToGrpcStatus(all.status());
    // The built-in default first, then by name: its key sorts first.
    auto page = Page(*all, request->page_size(), request->page_token(),
                     [](const reweight::NamedProfile& p) {
                       return p.profile.name == fusion::kDefaultProfileName ? std::string()
                                                                           : "n" + p.profile.name;
                     },
                     response->mutable_next_page_token());
    if (!page.ok()) return ToGrpcStatus(page.status());
    for (const reweight::NamedProfile* p : *page) {
      ProfileToProto(p->profile, p->created_utc, response->add_profiles());
    }
    response->set_active(active);
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* VaslServiceImpl::SetActiveProfile(
    grpc::CallbackServerContext* context, const v1::SetActiveProfileRequest* request,
    v1::WeightingProfile* response) {
  return RunUnary(context, *request, "SetActiveProfile", request->project(), Role::kWrite,
                  [this, request, response] {
    if (request->name().empty()) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "name the profile to activate");
    }
    absl::Status s = engine_->SetActiveProfile(request->project(), request->name());
    if (!s.ok()) return ToGrpcStatus(s);
    absl::StatusOr<reweight::NamedProfile> p =
        engine_->GetProfile(request->project(), request->name(), 0);
    if (!p.ok()) return ToGrpcStatus(p.status());
    ProfileToProto(p->profile, p->created_utc, response);
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* VaslServiceImpl::Reweight(grpc::CallbackServerContext* context,
                                                    const v1::ReweightRequest* request,
                                                    v1::ReweightResponse* response) {
  return RunChangeUnary(context, *request, "Reweight", request->project(), Role::kWrite,
                        [this, context, request, response] {
    if (request->revision() < 0) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "revision must be >= 0 (0: latest)");
    }
    const std::string& project = request->project();
    const std::string& request_id = request->request_id();
    const std::string subject = ReweightSubject(request->profile(), request->revision());
    std::optional<v1::Operation> committed;
    if (absl::Status s = StartOperation(project, request_id, "reweight", subject, &committed);
        !s.ok()) {
      return ToGrpcStatus(s);
    }
    if (committed) {
      *response = ReplayedAnswer(*committed, &v1::Operation::reweight);
      return grpc::Status::OK;
    }
    const ProgressFn progress = ProgressReporter(context, "Reweight", project,
                                                 "profile=" + request->profile(), Clock::now(),
                                                 request_id);
    absl::StatusOr<reweight::ReweightResult> r = engine_->Reweight(
        project, request->profile(), request->revision(), progress, request_id);
    UpdateProgress(project, [&](v1::IngestProgress& p) {
      p.set_state(r.ok() ? v1::IngestProgress::STATE_SUCCEEDED : v1::IngestProgress::STATE_FAILED);
      p.set_fraction(r.ok() ? 1.0 : p.fraction());
      p.set_message(r.ok() ? "" : std::string(r.status().message()));
    });
    const bool replayed = r.ok() && r->replayed;
    if (replayed) {  // it committed while this call waited for the writer lock
      *response = ReplayedAnswer(
          OperationFromRecord(project, {request_id, "reweight", subject, r->version, 0, r->answer}),
          &v1::Operation::reweight);
    } else if (r.ok()) {
      response->set_version(r->version);
      response->set_profile(r->profile);
      response->set_revision(r->revision);
      response->set_tile_count(r->tiles);
      response->set_record_count(r->records);
      response->set_vossel_count(r->vossels);
      response->set_bytes_written(r->bytes_written);
      response->set_unchanged(r->unchanged);
      response->set_seconds(r->seconds);
      response->set_request_id(request_id);
    }
    const grpc::Status status = r.ok() ? grpc::Status::OK : ToGrpcStatus(r.status());
    // An unchanged reweight committed nothing, so it has no operation row to answer from.
    EndOperation(project, request_id, status,
                 OperationWithAnswer(*response, &v1::Operation::mutable_reweight),
                 status.ok() && !replayed && !r->unchanged);
    return status;
  });
}

grpc::ServerUnaryReactor* VaslServiceImpl::QueryRecords(grpc::CallbackServerContext* context,
                                                        const v1::QueryRecordsRequest* request,
                                                        v1::QueryRecordsResponse* response) {
  return RunUnary(context, *request, "QueryRecords", request->project(), Role::kRead,
                  [this, request, response] {
    if (!request->has_min_m()) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                          "min_m is required: the point, or the box's low corner");
    }
    if (request->limit() < 0 || request->version() < 0) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "limit and version must be >= 0");
    }
    const auto vec = [](const v1::Vec3& v) { return Eigen::Vector3d(v.x(), v.y(), v.z()); };
    const Eigen::Vector3d lo = vec(request->min_m());
    const Eigen::Vector3d hi = request->has_max_m() ? vec(request->max_m()) : lo;
    const int64_t limit = request->limit() == 0 ? 10000 : std::min<int64_t>(request->limit(), 1000000);
    absl::StatusOr<flows::RecordsQueryResult> r = engine_->QueryRecords(
        request->project(), request->version(), lo, hi, request->profile(), limit);
    if (!r.ok()) return ToGrpcStatus(r.status());
    response->set_version(request->version());
    response->set_profile(r->profile);
    response->set_revision(r->revision);
    response->set_vossel_count(r->vossels);
    response->set_truncated(r->truncated);
    for (const flows::RecordRow& row : r->rows) RecordRowToProto(row, response->add_records());
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* VaslServiceImpl::Normalise(grpc::CallbackServerContext* context,
                                                     const v1::NormaliseRequest* request,
                                                     v1::NormaliseResponse* response) {
  return RunChangeUnary(context, *request, "Normalise", request->project(), Role::kWrite,
                        [this, request, response] {
    absl::StatusOr<reweight::NormaliseOutcome> r =
        engine_->Normalise(request->project(), request->base_profile(), request->name());
    if (!r.ok()) return ToGrpcStatus(r.status());
    ProfileToProto(r->profile.profile, r->profile.created_utc, response->mutable_profile());
    response->set_vossels_used(r->solve.vossels_used);
    response->set_pairs_used(r->solve.pairs_used);
    for (double c : r->solve.cost_before) response->add_cost_before(c);
    for (double c : r->solve.cost_after) response->add_cost_after(c);
    for (int32_t s : r->solve.unlinked_sources) response->add_unlinked_sources(s);
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* VaslServiceImpl::EstimateLens(grpc::CallbackServerContext* context,
                                                        const v1::EstimateLensRequest* request,
                                                        v1::EstimateLensResponse* response) {
  return RunChangeUnary(context, *request, "EstimateLens", request->project(), Role::kWrite,
                        [this, request, response] {
    if (request->cell_px() < 0) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "cell_px must be >= 0");
    }
    reweight::LensRequest lens;
    lens.rig = request->rig();
    lens.camera = request->camera();
    lens.from_utc = request->from_utc();
    lens.to_utc = request->to_utc();
    lens.name = request->name();
    lens.options.cell_px = request->cell_px();
    absl::StatusOr<reweight::LensOutcome> r =
        engine_->EstimateLens(request->project(), request->base_profile(), lens);
    if (!r.ok()) return ToGrpcStatus(r.status());
    ProfileToProto(r->profile.profile, r->profile.created_utc, response->mutable_profile());
    LensMapToProto(r->estimate.map, /*summary=*/false, response->mutable_map());
    response->set_samples(r->estimate.samples);
    response->set_cells(r->estimate.cells);
    response->set_cells_fitted(r->estimate.cells_fitted);
    response->set_cell_px(r->estimate.cell_px);
    response->set_residual_before(r->estimate.residual_before);
    response->set_residual_after(r->estimate.residual_after);
    response->set_replaced_map(r->replaced_map);
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* VaslServiceImpl::ListLensMaps(grpc::CallbackServerContext* context,
                                                        const v1::ListLensMapsRequest* request,
                                                        v1::ListLensMapsResponse* response) {
  return RunUnary(context, *request, "ListLensMaps", request->project(), Role::kRead,
                  [this, request, response] {
    absl::StatusOr<std::vector<fusion::LensMap>> maps = engine_->ListLensMaps(request->project());
    if (!maps.ok()) return ToGrpcStatus(maps.status());
    std::sort(maps->begin(), maps->end(),
              [](const fusion::LensMap& a, const fusion::LensMap& b) { return a.id < b.id; });
    auto page = Page(*maps, request->page_size(), request->page_token(),
                     [](const fusion::LensMap& m) { return IntKey(m.id); },
                     response->mutable_next_page_token());
    if (!page.ok()) return ToGrpcStatus(page.status());
    for (const fusion::LensMap* m : *page) {
      LensMapToProto(*m, request->summary(), response->add_maps());
    }
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* VaslServiceImpl::Rollback(grpc::CallbackServerContext* context,
                                                    const v1::RollbackRequest* request,
                                                    v1::ChangeResponse* response) {
  return RunChangeUnary(context, *request, "Rollback", request->project(), Role::kAdmin,
                        [this, context, request, response] {
    const ProgressFn progress =
        ProgressReporter(context, "Rollback", request->project(),
                         absl::StrCat("version=", request->version()), Clock::now());
    absl::StatusOr<IngestResult> result =
        engine_->Rollback(request->project(), request->version(), progress);
    return FinishChange(request->project(), result, response);
  });
}

grpc::ServerReadReactor<v1::BackProjectRequest>* VaslServiceImpl::BackProject(
    grpc::CallbackServerContext* context, v1::BackProjectResponse* response) {
  return new BackProjectReactor(this, context, response);
}

namespace {

Role RoleFromProto(v1::Role role) {
  switch (role) {
    case v1::ROLE_READ: return Role::kRead;
    case v1::ROLE_WRITE: return Role::kWrite;
    case v1::ROLE_ADMIN: return Role::kAdmin;
    default: return Role::kNone;
  }
}

void TokenToProto(const TokenInfo& t, v1::AccessToken* out) {
  out->set_id(t.id);
  out->set_project(t.project);
  out->set_role(static_cast<v1::Role>(static_cast<int>(t.role)));
  out->set_label(t.label);
  out->set_created_by(t.created_by);
  TimestampFromIso(t.created_utc, out->mutable_create_time());
  if (!t.revoked_utc.empty()) TimestampFromIso(t.revoked_utc, out->mutable_revoke_time());
}

}  // namespace

grpc::ServerUnaryReactor* VaslServiceImpl::CreateToken(grpc::CallbackServerContext* context,
                                                       const v1::CreateTokenRequest* request,
                                                       v1::AccessToken* response) {
  return RunUnary(context, *request, "CreateToken", request->project(), Role::kNone,
                  [this, request, response](const Caller& caller) {
    if (absl::Status s = AccessControl::Require(caller, request->project(), Role::kAdmin,
                                                "creating a token");
        !s.ok()) {
      return ToGrpcStatus(s);
    }
    if (request->project() != kAllProjects) {
      absl::StatusOr<ProjectInfo> info = engine_->GetProject(request->project());
      if (!info.ok()) return ToGrpcStatus(info.status());
    }
    auto made = access_->Create(caller, request->project(), RoleFromProto(request->role()),
                                request->label());
    if (!made.ok()) return ToGrpcStatus(made.status());
    TokenToProto(made->first, response);
    response->set_token(made->second);
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* VaslServiceImpl::ListTokens(grpc::CallbackServerContext* context,
                                                      const v1::ListTokensRequest* request,
                                                      v1::ListTokensResponse* response) {
  return RunUnary(context, *request, "ListTokens", request->project(), Role::kNone,
                  [this, request, response](const Caller& caller) {
    auto tokens = access_->List(caller, request->project());
    if (!tokens.ok()) return ToGrpcStatus(tokens.status());
    for (const TokenInfo& t : *tokens) TokenToProto(t, response->add_tokens());
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* VaslServiceImpl::RevokeToken(grpc::CallbackServerContext* context,
                                                       const v1::RevokeTokenRequest* request,
                                                       v1::AccessToken* response) {
  return RunUnary(context, *request, "RevokeToken", "", Role::kNone,
                  [this, request, response](const Caller& caller) {
    auto revoked = access_->Revoke(caller, request->id());
    if (!revoked.ok()) return ToGrpcStatus(revoked.status());
    TokenToProto(*revoked, response);
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* VaslServiceImpl::PinVersion(grpc::CallbackServerContext* context,
                                                      const v1::PinVersionRequest* request,
                                                      v1::Version* response) {
  return RunUnary(context, *request, "PinVersion", request->project(), Role::kAdmin,
                  [this, request, response] {
    absl::Status s = engine_->SetPinned(request->project(), request->version(), request->pinned());
    if (!s.ok()) return ToGrpcStatus(s);
    absl::StatusOr<std::vector<store::VersionInfo>> versions = engine_->ListVersions(request->project());
    if (!versions.ok()) return ToGrpcStatus(versions.status());
    for (const store::VersionInfo& v : *versions) {
      if (v.version == request->version()) VersionToProto(v, response);
    }
    return grpc::Status::OK;
  });
}

}  // namespace vasl::server

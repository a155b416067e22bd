/// @file vasl_service.h
/// @brief The vasl.v1.VaslService adapter: a thin callback service holding a pointer to the
///        lattice Engine. Each RPC validates, converts from proto, hands the blocking engine call
///        to a WorkerPool thread, converts back and maps the status (status_util.h).
/// @details One reactor per streaming RPC (IngestScan reads, Render writes), as in gRPC's
///          route_guide callback example; unary RPCs use the context's default reactor. No
///          engine call runs on a gRPC callback thread. One log line per request (method,
///          project, status code, duration in ms) goes to the log sink; ingest progress is both
///          logged per stage and served by GetIngestProgress.
/// @warning Thread-safe. The Engine and WorkerPool must outlive the service.
#pragma once

#include <atomic>
#include <chrono>
#include <deque>
#include <filesystem>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <string>

#include "lattice/engine.h"
#include "server/access.h"
#include "server/operations.h"
#include "server/worker_pool.h"
#include "vasl/v1/vasl.grpc.pb.h"

namespace vasl::server {

/// Receives one formatted log line (no trailing newline). Default: stderr with a UTC time.
using LogSink = std::function<void(const std::string& line)>;
void StderrLogSink(const std::string& line);

struct ServiceOptions {
  /// Payload size of streamed render chunks, bytes.
  int64_t render_chunk_bytes = 1ll << 20;
  LogSink log = StderrLogSink;
  /// Where Export stages merged files before streaming them (vasld: its data directory);
  /// empty: the system's temp directory.
  std::filesystem::path staging_dir;
  /// Who may call what (server/access.h); null: access control off.
  AccessControl* access = nullptr;
  /// Calls one client (one peer address) may have running at once; 0: no bound.
  int max_calls_per_client = 0;
  /// Bytes of incoming scans and images all ingest and back-projection streams may hold at
  /// once (received, not yet committed); 0: no bound.
  int64_t max_inflight_ingest_bytes = 0;
  /// Calls that write project data (ingest, back-projection, write-role RPCs, CreateProject)
  /// are refused while staging_dir's file system has fewer free bytes; 0: no floor.
  int64_t min_free_disk_bytes = 0;
  /// Runs the calls that change a project (ingest, back-projection, rebuild, deletion,
  /// reweight, rollback, normalisation), so that however long they take they never hold up
  /// renders and reads, which the service's own pool runs; null: that pool runs everything.
  WorkerPool* change_pool = nullptr;
  /// Mutual TLS is on (vasld --tls-client-ca): every call of this service must come with a
  /// verified client certificate (UNAUTHENTICATED without). The transport only verifies a
  /// certificate a client presents, so that health checks (and reflection) stay open.
  bool require_client_certificate = false;
};

/// OK while the caller of `context` still waits for its work (nullptr: always); CANCELLED
/// once it cancelled the call or went away, DEADLINE_EXCEEDED once its deadline passed. The
/// engine's long work asks it between stages and rows (ProgressFn, RenderRequest::interrupt),
/// so a call nobody waits for stops and frees its memory. Callable from any thread until the
/// call is finished.
absl::Status StillWanted(grpc::CallbackServerContext* context);

class VaslServiceImpl final : public v1::VaslService::CallbackService {
 public:
  VaslServiceImpl(Engine* engine, WorkerPool* pool, ServiceOptions options = {});

  grpc::ServerUnaryReactor* CreateProject(grpc::CallbackServerContext* context,
                                          const v1::CreateProjectRequest* request,
                                          v1::Project* response) override;
  grpc::ServerUnaryReactor* GetProject(grpc::CallbackServerContext* context,
                                       const v1::GetProjectRequest* request,
                                       v1::Project* response) override;
  grpc::ServerUnaryReactor* ListProjects(grpc::CallbackServerContext* context,
                                         const v1::ListProjectsRequest* request,
                                         v1::ListProjectsResponse* response) override;
  grpc::ServerUnaryReactor* ListScans(grpc::CallbackServerContext* context,
                                      const v1::ListScansRequest* request,
                                      v1::ListScansResponse* response) override;
  grpc::ServerReadReactor<v1::IngestScanRequest>* IngestScan(
      grpc::CallbackServerContext* context, v1::IngestScanResponse* response) override;
  grpc::ServerUnaryReactor* GetIngestProgress(grpc::CallbackServerContext* context,
                                              const v1::GetIngestProgressRequest* request,
                                              v1::IngestProgress* response) override;
  grpc::ServerUnaryReactor* GetOperation(grpc::CallbackServerContext* context,
                                         const v1::GetOperationRequest* request,
                                         v1::Operation* response) override;
  grpc::ServerWriteReactor<v1::RenderResponse>* Render(
      grpc::CallbackServerContext* context, const v1::RenderRequest* request) override;
  grpc::ServerUnaryReactor* InspectRecords(grpc::CallbackServerContext* context,
                                           const v1::InspectRecordsRequest* request,
                                           v1::InspectRecordsResponse* response) override;

  grpc::ServerUnaryReactor* Rebuild(grpc::CallbackServerContext* context,
                                    const v1::RebuildRequest* request,
                                    v1::ChangeResponse* response) override;
  grpc::ServerUnaryReactor* DeleteScan(grpc::CallbackServerContext* context,
                                       const v1::DeleteScanRequest* request,
                                       v1::ChangeResponse* response) override;
  grpc::ServerUnaryReactor* ListVersions(grpc::CallbackServerContext* context,
                                         const v1::ListVersionsRequest* request,
                                         v1::ListVersionsResponse* response) override;
  grpc::ServerUnaryReactor* CreateProfile(grpc::CallbackServerContext* context,
                                          const v1::CreateProfileRequest* request,
                                          v1::WeightingProfile* response) override;
  grpc::ServerUnaryReactor* GetProfile(grpc::CallbackServerContext* context,
                                       const v1::GetProfileRequest* request,
                                       v1::WeightingProfile* response) override;
  grpc::ServerUnaryReactor* ListProfiles(grpc::CallbackServerContext* context,
                                         const v1::ListProfilesRequest* request,
                                         v1::ListProfilesResponse* response) override;
  grpc::ServerUnaryReactor* SetActiveProfile(grpc::CallbackServerContext* context,
                                             const v1::SetActiveProfileRequest* request,
                                             v1::WeightingProfile* response) override;
  grpc::ServerUnaryReactor* Reweight(grpc::CallbackServerContext* context,
                                     const v1::ReweightRequest* request,
                                     v1::ReweightResponse* response) override;
  grpc::ServerUnaryReactor* QueryRecords(grpc::CallbackServerContext* context,
                                         const v1::QueryRecordsRequest* request,
                                         v1::QueryRecordsResponse* response) override;
  grpc::ServerUnaryReactor* Normalise(grpc::CallbackServerContext* context,
                                      const v1::NormaliseRequest* request,
                                      v1::NormaliseResponse* response) override;
  grpc::ServerUnaryReactor* EstimateLens(grpc::CallbackServerContext* context,
                                         const v1::EstimateLensRequest* request,
                                         v1::EstimateLensResponse* response) override;
  grpc::ServerUnaryReactor* ListLensMaps(grpc::CallbackServerContext* context,
                                         const v1::ListLensMapsRequest* request,
                                         v1::ListLensMapsResponse* response) override;
  grpc::ServerUnaryReactor* Rollback(grpc::CallbackServerContext* context,
                                     const v1::RollbackRequest* request,
                                     v1::ChangeResponse* response) override;
  grpc::ServerReadReactor<v1::BackProjectRequest>* BackProject(
      grpc::CallbackServerContext* context, v1::BackProjectResponse* response) override;
  grpc::ServerUnaryReactor* CreateToken(grpc::CallbackServerContext* context,
                                        const v1::CreateTokenRequest* request,
                                        v1::AccessToken* response) override;
  grpc::ServerUnaryReactor* ListTokens(grpc::CallbackServerContext* context,
                                       const v1::ListTokensRequest* request,
                                       v1::ListTokensResponse* response) override;
  grpc::ServerUnaryReactor* RevokeToken(grpc::CallbackServerContext* context,
                                        const v1::RevokeTokenRequest* request,
                                        v1::AccessToken* response) override;
  grpc::ServerUnaryReactor* PinVersion(grpc::CallbackServerContext* context,
                                       const v1::PinVersionRequest* request,
                                       v1::Version* response) override;
  grpc::ServerWriteReactor<v1::ExportResponse>* Export(
      grpc::CallbackServerContext* context, const v1::ExportRequest* request) override;
  grpc::ServerWriteReactor<v1::GetVisualReferenceResponse>* GetVisualReference(
      grpc::CallbackServerContext* context, const v1::GetVisualReferenceRequest* request) override;
  grpc::ServerWriteReactor<v1::GetConfidenceResponse>* GetConfidence(
      grpc::CallbackServerContext* context, const v1::GetConfidenceRequest* request) override;

  // Used by the reactors (vasl_service.cc).
  /// A progress callback for a long engine call: it updates the progress board of `project`
  /// (GetIngestProgress) and logs one line per stage ("<method> progress project=… <what> …").
  /// With a `request_id`, the operation's stage follows too (GetOperation).
  /// Its answer stops the work once the call is cancelled or its deadline passes (StillWanted;
  /// no check without a `context`).
  ProgressFn ProgressReporter(grpc::CallbackServerContext* context, const char* method,
                              const std::string& project,
                              const std::string& what, std::chrono::steady_clock::time_point start,
                              const std::string& request_id = "");
  /// Before a change sent under `request_id` runs (nothing for an empty id): OK with
  /// `*committed` set when it committed before (the call answers from it, replayed), else OK
  /// having marked it running (end it with EndOperation); ABORTED while it runs,
  /// INVALID_ARGUMENT for a malformed id, FAILED_PRECONDITION when the id named another change.
  absl::Status StartOperation(const std::string& project, const std::string& request_id,
                              const std::string& kind, const std::string& subject,
                              std::optional<v1::Operation>* committed);
  /// After a change StartOperation marked running: on success `done` (version and answer set)
  /// is kept in memory and, with `record`, as the answer in the project's catalog; else the
  /// failure is kept in memory.
  void EndOperation(const std::string& project, const std::string& request_id,
                    const grpc::Status& status, const v1::Operation& done, bool record);
  /// Where Export stages its files (the data directory's .tmp-export-*).
  std::filesystem::path ExportStagingPath() const;
  Engine* engine() const { return engine_; }
  WorkerPool* pool() const { return pool_; }
  WorkerPool* change_pool() const { return options_.change_pool ? options_.change_pool : pool_; }
  const ServiceOptions& options() const { return options_; }
  /// One request log line: method, project, code, duration (and the message on error).
  void LogRequest(const char* method, const std::string& project, const grpc::Status& status,
                  std::chrono::steady_clock::time_point start) const;
  /// The caller of `context` (its `authorization` metadata); UNAUTHENTICATED when access
  /// control is on and it carries no valid token.
  absl::StatusOr<Caller> Authenticate(const grpc::CallbackServerContext* context) const;
  /// Authenticate, then require `need` on `project` (Role::kNone: authentication only);
  /// the caller, or UNAUTHENTICATED / PERMISSION_DENIED.
  absl::StatusOr<Caller> Authorize(const grpc::CallbackServerContext* context,
                                   const std::string& project, Role need,
                                   const char* method) const;
  /// Takes one of the caller's concurrent-call slots (ServiceOptions::max_calls_per_client);
  /// RESOURCE_EXHAUSTED naming the limit when it has none left. Release with ReleaseSlot.
  absl::Status AcquireSlot(const grpc::CallbackServerContext* context, std::string* client);
  void ReleaseSlot(const std::string& client);
  /// Counts `delta` bytes more (or fewer) held by incoming streams; RESOURCE_EXHAUSTED naming
  /// the limit when more would exceed ServiceOptions::max_inflight_ingest_bytes (then nothing
  /// is counted).
  /// RESOURCE_EXHAUSTED while the data directory's file system has fewer free bytes than
  /// ServiceOptions::min_free_disk_bytes: a write refused before it starts, nothing written
  /// (an ingest that runs the disk full mid-commit fails too, but only after the upload).
  absl::Status CheckDiskFloor() const;
  absl::Status HoldIngestBytes(int64_t delta);
  /// Updates the progress board of `project` (thread-safe).
  void UpdateProgress(const std::string& project,
                      const std::function<void(v1::IngestProgress&)>& update);
  v1::IngestProgress GetProgress(const std::string& project);

 private:
  /// Checks the request's text fields (CheckRequestStrings), then that the caller holds `need`
  /// on `project` (Authorize), then runs `body` (which fills the response and returns a
  /// status) on `lane` with the caller, then logs and finishes the unary reactor.
  grpc::ServerUnaryReactor* RunOn(WorkerPool* lane, grpc::CallbackServerContext* context,
                                  const google::protobuf::Message& request, const char* method,
                                  const std::string& project, Role need,
                                  std::function<grpc::Status(const Caller&)> body);
  /// RunOn the pool (reads and quick calls), with or without the caller.
  grpc::ServerUnaryReactor* RunUnary(grpc::CallbackServerContext* context,
                                     const google::protobuf::Message& request, const char* method,
                                     const std::string& project, Role need,
                                     std::function<grpc::Status(const Caller&)> body) {
    return RunOn(pool_, context, request, method, project, need, std::move(body));
  }
  grpc::ServerUnaryReactor* RunUnary(grpc::CallbackServerContext* context,
                                     const google::protobuf::Message& request, const char* method,
                                     const std::string& project, Role need,
                                     std::function<grpc::Status()> body) {
    return RunOn(pool_, context, request, method, project, need,
                 [body = std::move(body)](const Caller&) { return body(); });
  }
  /// RunOn the change pool: a call that makes a new version of a project.
  grpc::ServerUnaryReactor* RunChangeUnary(grpc::CallbackServerContext* context,
                                           const google::protobuf::Message& request,
                                           const char* method, const std::string& project,
                                           Role need, std::function<grpc::Status()> body) {
    return RunOn(change_pool(), context, request, method, project, need,
                 [body = std::move(body)](const Caller&) { return body(); });
  }
  /// Logs and finishes a unary call that was refused before any work.
  grpc::ServerUnaryReactor* Deny(grpc::CallbackServerContext* context, const char* method,
                                 const std::string& project, const grpc::Status& status);
  /// A rebuild or deletion (`change`) under `request_id` (StartOperation, EndOperation): answered
  /// from its commit when it committed before, else run with a progress reporter.
  grpc::Status RunChange(grpc::CallbackServerContext* context, const std::string& project,
                         const std::string& request_id,
                         const std::string& kind, const std::string& subject,
                         v1::ChangeResponse* response,
                         const std::function<absl::StatusOr<IngestResult>(const ProgressFn&)>& change);
  /// Marks a rebuild or deletion finished on the progress board and fills its response.
  grpc::Status FinishChange(const std::string& project, const absl::StatusOr<IngestResult>& result,
                            v1::ChangeResponse* response);

  Engine* engine_;
  WorkerPool* pool_;
  ServiceOptions options_;
  std::unique_ptr<AccessControl> open_access_;  // used when options_.access is null
  AccessControl* access_ = nullptr;
  std::mutex progress_mutex_;
  std::map<std::string, v1::IngestProgress> progress_;
  std::deque<std::string> progress_order_;  // oldest first, for the board's bound
  std::mutex slots_mutex_;
  std::map<std::string, int> slots_;  // running calls per peer address
  std::atomic<int64_t> inflight_ingest_bytes_{0};
  OperationTracker operations_;
};

}  // namespace vasl::server

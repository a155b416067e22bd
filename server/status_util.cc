/// @file status_util.cc
/// @brief absl::Status -> grpc::Status (ARCHITECTURE.md, "Errors and limits").
#include "server/status_util.h"

#include <algorithm>
#include <atomic>
#include <memory>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_replace.h"

namespace vasl::server {
namespace {

struct Redaction {
  std::vector<std::string> hidden_paths;
  std::function<void(const std::string&)> log;
};

std::shared_ptr<const Redaction>& CurrentRedaction() {
  static std::shared_ptr<const Redaction> current;
  return current;
}

std::atomic<uint64_t> error_reference{0};

}  // namespace

void RedactStatuses(std::vector<std::string> hidden_paths,
                    std::function<void(const std::string&)> log) {
  auto r = std::make_shared<Redaction>();
  for (std::string& p : hidden_paths) {
    while (p.size() > 1 && p.back() == '/') p.pop_back();
    if (p.size() > 1 && p[0] == '/') r->hidden_paths.push_back(std::move(p));  // absolute only
  }
  // Longest first, so that a path inside another is not half replaced.
  std::sort(r->hidden_paths.begin(), r->hidden_paths.end(),
            [](const std::string& a, const std::string& b) { return a.size() > b.size(); });
  r->log = std::move(log);
  CurrentRedaction() = std::move(r);
}

grpc::StatusCode ToGrpcCode(absl::StatusCode code) {
  switch (code) {
    case absl::StatusCode::kOk: return grpc::StatusCode::OK;
    case absl::StatusCode::kCancelled: return grpc::StatusCode::CANCELLED;
    case absl::StatusCode::kUnknown: return grpc::StatusCode::UNKNOWN;
    case absl::StatusCode::kInvalidArgument: return grpc::StatusCode::INVALID_ARGUMENT;
    case absl::StatusCode::kDeadlineExceeded: return grpc::StatusCode::DEADLINE_EXCEEDED;
    case absl::StatusCode::kNotFound: return grpc::StatusCode::NOT_FOUND;
    case absl::StatusCode::kAlreadyExists: return grpc::StatusCode::ALREADY_EXISTS;
    case absl::StatusCode::kPermissionDenied: return grpc::StatusCode::PERMISSION_DENIED;
    case absl::StatusCode::kResourceExhausted: return grpc::StatusCode::RESOURCE_EXHAUSTED;
    case absl::StatusCode::kFailedPrecondition: return grpc::StatusCode::FAILED_PRECONDITION;
    case absl::StatusCode::kAborted: return grpc::StatusCode::ABORTED;
    case absl::StatusCode::kOutOfRange: return grpc::StatusCode::OUT_OF_RANGE;
    case absl::StatusCode::kUnimplemented: return grpc::StatusCode::UNIMPLEMENTED;
    case absl::StatusCode::kInternal: return grpc::StatusCode::INTERNAL;
    case absl::StatusCode::kUnavailable: return grpc::StatusCode::UNAVAILABLE;
    case absl::StatusCode::kDataLoss: return grpc::StatusCode::DATA_LOSS;
    case absl::StatusCode::kUnauthenticated: return grpc::StatusCode::UNAUTHENTICATED;
    default: return grpc::StatusCode::UNKNOWN;
  }
}

grpc::Status ToGrpcStatus(const absl::Status& status) {
  if (status.ok()) return grpc::Status::OK;
  const grpc::StatusCode code = ToGrpcCode(status.code());
  std::string message(status.message());
  const std::shared_ptr<const Redaction> r = CurrentRedaction();
  if (!r) return grpc::Status(code, message);
  const bool internal = code == grpc::StatusCode::INTERNAL || code == grpc::StatusCode::UNKNOWN ||
                        absl::StrContains(message, "catalog statement") ||
                        absl::StrContains(message, "cannot prepare");
  if (internal) {
    const uint64_t ref = error_reference.fetch_add(1) + 1;
    if (r->log) {
      r->log(absl::StrCat("error reference E", ref, ": ", GrpcCodeName(code), ": ", message));
    }
    return grpc::Status(code, absl::StrCat("the server failed on this request (reference E", ref,
                                           " in its log)"));
  }
  return grpc::Status(code, RedactPaths(std::move(message)));
}

std::string RedactPaths(std::string text) {
  const std::shared_ptr<const Redaction> r = CurrentRedaction();
  if (!r) return text;
  for (const std::string& path : r->hidden_paths) {
    text = absl::StrReplaceAll(text, {{path, "<data-dir>"}});
  }
  return text;
}

const char* GrpcCodeName(grpc::StatusCode code) {
  switch (code) {
    case grpc::StatusCode::OK: return "OK";
    case grpc::StatusCode::CANCELLED: return "CANCELLED";
    case grpc::StatusCode::UNKNOWN: return "UNKNOWN";
    case grpc::StatusCode::INVALID_ARGUMENT: return "INVALID_ARGUMENT";
    case grpc::StatusCode::DEADLINE_EXCEEDED: return "DEADLINE_EXCEEDED";
    case grpc::StatusCode::NOT_FOUND: return "NOT_FOUND";
    case grpc::StatusCode::ALREADY_EXISTS: return "ALREADY_EXISTS";
    case grpc::StatusCode::PERMISSION_DENIED: return "PERMISSION_DENIED";
    case grpc::StatusCode::RESOURCE_EXHAUSTED: return "RESOURCE_EXHAUSTED";
    case grpc::StatusCode::FAILED_PRECONDITION: return "FAILED_PRECONDITION";
    case grpc::StatusCode::ABORTED: return "ABORTED";
    case grpc::StatusCode::OUT_OF_RANGE: return "OUT_OF_RANGE";
    case grpc::StatusCode::UNIMPLEMENTED: return "UNIMPLEMENTED";
    case grpc::StatusCode::INTERNAL: return "INTERNAL";
    case grpc::StatusCode::UNAVAILABLE: return "UNAVAILABLE";
    case grpc::StatusCode::DATA_LOSS: return "DATA_LOSS";
    case grpc::StatusCode::UNAUTHENTICATED: return "UNAUTHENTICATED";
    default: return "UNKNOWN";
  }
}

}  // namespace vasl::server

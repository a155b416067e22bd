/// @file status_util.h
/// @brief The one place where lattice errors (absl::Status) become gRPC statuses
///        (ARCHITECTURE.md, "Errors and limits").
/// @details Every code keeps its meaning: INVALID_ARGUMENT for bad input, NOT_FOUND,
///          ALREADY_EXISTS, FAILED_PRECONDITION, RESOURCE_EXHAUSTED for limits, UNAUTHENTICATED,
///          PERMISSION_DENIED, INTERNAL only for bugs. Lattice messages are written for the user
///          and pass through, with two exceptions (RedactStatuses): the server's own paths are
///          replaced by `<data-dir>`, and the text of INTERNAL, UNKNOWN and store (SQL) errors
///          goes to the server log under a reference that the client's message cites.
#pragma once

#include <functional>
#include <string>
#include <vector>

#include <grpcpp/support/status.h>

#include "absl/status/status.h"

namespace vasl::server {

/// absl::StatusCode -> grpc::StatusCode; an unknown value maps to UNKNOWN.
grpc::StatusCode ToGrpcCode(absl::StatusCode code);
/// absl::Status -> grpc::Status with the same message (redacted, see RedactStatuses).
grpc::Status ToGrpcStatus(const absl::Status& status);
/// `text` with the hidden paths replaced (for messages sent as data, e.g. Project.problem).
std::string RedactPaths(std::string text);
/// Server-wide, once at start-up: paths to hide from clients (each shown as `<data-dir>`), and
/// where the full text of an internal error goes. Until called, messages pass unchanged.
void RedactStatuses(std::vector<std::string> hidden_paths,
                    std::function<void(const std::string&)> log);
/// Name of a gRPC code as in the gRPC docs ("INVALID_ARGUMENT"), for logs.
const char* GrpcCodeName(grpc::StatusCode code);

}  // namespace vasl::server

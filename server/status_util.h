/// @file status_util.h
/// @brief The one place where lattice errors (absl::Status) become gRPC statuses
///        (ARCHITECTURE.md, "Errors and limits").
/// @details Every code keeps its meaning: INVALID_ARGUMENT for bad input, NOT_FOUND,
///          ALREADY_EXISTS, FAILED_PRECONDITION, RESOURCE_EXHAUSTED for limits, UNAUTHENTICATED,
///          PERMISSION_DENIED, INTERNAL only for bugs. The message is passed through unchanged:
///          lattice messages are written for the user.
#pragma once

#include <string>

#include <grpcpp/support/status.h>

#include "absl/status/status.h"

namespace vasl::server {

/// absl::StatusCode -> grpc::StatusCode; an unknown value maps to UNKNOWN.
grpc::StatusCode ToGrpcCode(absl::StatusCode code);
/// absl::Status -> grpc::Status with the same message.
grpc::Status ToGrpcStatus(const absl::Status& status);
/// Name of a gRPC code as in the gRPC docs ("INVALID_ARGUMENT"), for logs.
const char* GrpcCodeName(grpc::StatusCode code);

}  // namespace vasl::server

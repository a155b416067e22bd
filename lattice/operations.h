/// @file operations.h
/// @brief Changes asked for under a client's request id (engine.h FindOperation): a retry of a
///        change that committed is answered from the catalog instead of being done again.
#pragma once

#include <optional>
#include <string>

#include "absl/status/statusor.h"
#include "lattice/engine.h"
#include "lattice/store/project_store.h"

namespace vasl {

/// The change committed under `asked.request_id` in `store`, or nullopt when the id is new.
/// With `asked.kind` set, FAILED_PRECONDITION when the id was used for another change (kind or
/// subject differ). INVALID_ARGUMENT for a malformed id.
absl::StatusOr<std::optional<store::OperationRecord>> FindCommitted(
    const store::ProjectStore& store, const store::OperationRecord& asked);

/// The subject a reweight is recorded under: the profile as asked, "NAME@REVISION", "active"
/// for the project's active profile and "latest" for revision 0.
std::string ReweightSubject(const std::string& profile, int32_t revision);

/// With a request id (`op.request_id` non-empty): the change committed under it as a replayed
/// IngestResult (FindCommitted), or nullopt when it must run (its commit then records it).
/// Call with the writer lock held.
absl::StatusOr<std::optional<IngestResult>> ReplayOperation(const store::ProjectStore& store,
                                                            const store::OperationRecord& op);

/// ReplayOperation for a reweight: the one committed under `op.request_id` as a replayed
/// ReweightResult (its version and recorded answer), or nullopt when it must run.
absl::StatusOr<std::optional<reweight::ReweightResult>> ReplayReweight(
    const store::ProjectStore& store, const store::OperationRecord& op);

}  // namespace vasl

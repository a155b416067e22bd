/// @file operations.h
/// @brief Changes sent under a client's request id (GetOperation): running and recently
///        finished ones as this server saw them; committed ones also in the project's catalog
///        (Engine::FindOperation), which outlives the server.
#pragma once

#include <chrono>
#include <cstdint>
#include <deque>
#include <map>
#include <mutex>
#include <optional>
#include <string>
#include <utility>

#include <grpcpp/grpcpp.h>

#include "absl/status/status.h"
#include "lattice/store/project_store.h"
#include "vasl/v1/vasl.pb.h"

namespace vasl::server {

class OperationTracker {
 public:
  /// Keeps the last `keep_finished` finished changes (the running ones always).
  explicit OperationTracker(size_t keep_finished = 4096) : keep_finished_(keep_finished) {}

  /// Marks (project, id) running; ABORTED, naming its stage, when it is running already.
  absl::Status Begin(const std::string& project, const std::string& id, const std::string& kind,
                     const std::string& subject);
  /// The stage of a running change.
  void Progress(const std::string& project, const std::string& id, const std::string& stage,
                double fraction);
  /// Ends a running change: SUCCEEDED with `done` (version and answer set), or FAILED.
  void Succeed(const std::string& project, const std::string& id, const v1::Operation& done);
  void Fail(const std::string& project, const std::string& id, const grpc::Status& status);
  /// The change as this server saw it (elapsed_s current for a running one), or nullopt.
  std::optional<v1::Operation> Get(const std::string& project, const std::string& id) const;

 private:
  using Key = std::pair<std::string, std::string>;
  struct Entry {
    v1::Operation op;
    std::chrono::steady_clock::time_point start;
  };
  void Retire(const Key& key);  // with mu_ held

  mutable std::mutex mu_;
  std::map<Key, Entry> ops_;
  std::deque<Key> finished_;  // oldest first
  size_t keep_finished_;
};

/// The Operation of a committed change as the catalog recorded it: its answer when the call
/// recorded one (a serialized Operation), else what the record itself holds.
v1::Operation OperationFromRecord(const std::string& project, const store::OperationRecord& rec);

/// The call's response kept as an Operation's answer (`slot`: its mutable accessor, e.g.
/// &v1::Operation::mutable_ingest), with its version.
template <typename Response>
v1::Operation OperationWithAnswer(const Response& response, Response* (v1::Operation::*slot)()) {
  v1::Operation op;
  op.set_version(response.version());
  *(op.*slot)() = response;
  return op;
}

/// The answer to a retry of a change that committed: `committed`'s answer (`answer`: its
/// accessor, e.g. &v1::Operation::ingest), marked replayed under its request id.
template <typename Response>
Response ReplayedAnswer(const v1::Operation& committed,
                        const Response& (v1::Operation::*answer)() const) {
  Response response = (committed.*answer)();
  response.set_request_id(committed.request_id());
  response.set_replayed(true);
  return response;
}

}  // namespace vasl::server

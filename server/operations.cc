#include "server/operations.h"

#include "absl/strings/str_cat.h"

namespace vasl::server {

absl::Status OperationTracker::Begin(const std::string& project, const std::string& id,
                                     const std::string& kind, const std::string& subject) {
  std::lock_guard<std::mutex> lock(mu_);
  const Key key{project, id};
  auto it = ops_.find(key);
  if (it != ops_.end() && it->second.op.state() == v1::Operation::STATE_RUNNING) {
    return absl::AbortedError(absl::StrCat(
        "request \"", id, "\" (", it->second.op.kind(), ") is still running (stage \"",
        it->second.op.stage(), "\"): poll GetOperation for its answer instead of sending it again"));
  }
  if (it != ops_.end()) {  // finished before: it runs again (a failure stored nothing)
    for (auto f = finished_.begin(); f != finished_.end(); ++f) {
      if (*f == key) {
        finished_.erase(f);
        break;
      }
    }
  }
  Entry& e = ops_[key];
  e.op = v1::Operation();
  e.op.set_project(project);
  e.op.set_request_id(id);
  e.op.set_kind(kind);
  e.op.set_subject(subject);
  e.op.set_state(v1::Operation::STATE_RUNNING);
  e.op.set_stage("received");
  e.start = std::chrono::steady_clock::now();
  return absl::OkStatus();
}

void OperationTracker::Progress(const std::string& project, const std::string& id,
                                const std::string& stage, double fraction) {
  std::lock_guard<std::mutex> lock(mu_);
  auto it = ops_.find({project, id});
  if (it == ops_.end() || it->second.op.state() != v1::Operation::STATE_RUNNING) return;
  it->second.op.set_stage(stage);
  it->second.op.set_fraction(fraction);
}

void OperationTracker::Retire(const Key& key) {
  finished_.push_back(key);
  while (finished_.size() > keep_finished_) {
    ops_.erase(finished_.front());
    finished_.pop_front();
  }
}

void OperationTracker::Succeed(const std::string& project, const std::string& id,
                               const v1::Operation& done) {
  std::lock_guard<std::mutex> lock(mu_);
  auto it = ops_.find({project, id});
  if (it == ops_.end()) return;
  const double elapsed =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - it->second.start).count();
  v1::Operation op = done;  // the answer, under the running entry's identity
  op.set_project(it->second.op.project());
  op.set_request_id(it->second.op.request_id());
  op.set_kind(it->second.op.kind());
  op.set_subject(it->second.op.subject());
  it->second.op = std::move(op);
  it->second.op.set_state(v1::Operation::STATE_SUCCEEDED);
  it->second.op.set_stage("done");
  it->second.op.set_fraction(1.0);
  it->second.op.set_elapsed_s(elapsed);
  Retire(it->first);
}

void OperationTracker::Fail(const std::string& project, const std::string& id,
                            const grpc::Status& status) {
  std::lock_guard<std::mutex> lock(mu_);
  auto it = ops_.find({project, id});
  if (it == ops_.end()) return;
  v1::Operation& op = it->second.op;
  op.set_state(v1::Operation::STATE_FAILED);
  op.set_error_code(int32_t(status.error_code()));
  op.set_error_message(status.error_message());
  op.set_elapsed_s(
      std::chrono::duration<double>(std::chrono::steady_clock::now() - it->second.start).count());
  Retire(it->first);
}

std::optional<v1::Operation> OperationTracker::Get(const std::string& project,
                                                   const std::string& id) const {
  std::lock_guard<std::mutex> lock(mu_);
  auto it = ops_.find({project, id});
  if (it == ops_.end()) return std::nullopt;
  v1::Operation op = it->second.op;
  if (op.state() == v1::Operation::STATE_RUNNING) {
    op.set_elapsed_s(
        std::chrono::duration<double>(std::chrono::steady_clock::now() - it->second.start).count());
  }
  return op;
}

v1::Operation OperationFromRecord(const std::string& project, const store::OperationRecord& rec) {
  v1::Operation op;
  if (rec.answer.empty() || !op.ParseFromString(rec.answer)) {
    // Committed, but the server stopped before it recorded the call's answer.
    op = v1::Operation();
    if (rec.kind == "ingest") {
      op.mutable_ingest()->set_scan_id(rec.scan_id);
      op.mutable_ingest()->set_scan(rec.subject);
      op.mutable_ingest()->set_version(rec.version);
    } else if (rec.kind == "back-project") {
      op.mutable_back_project()->set_name(rec.subject);
      op.mutable_back_project()->set_version(rec.version);
    } else if (rec.kind == "reweight") {
      op.mutable_reweight()->set_version(rec.version);
    } else {
      op.mutable_change()->set_version(rec.version);
    }
  }
  op.set_project(project);
  op.set_request_id(rec.request_id);
  op.set_kind(rec.kind);
  op.set_subject(rec.subject);
  op.set_state(v1::Operation::STATE_SUCCEEDED);
  op.set_stage("done");
  op.set_fraction(1.0);
  op.set_version(rec.version);
  return op;
}

}  // namespace vasl::server

#include "lattice/operations.h"

#include "absl/strings/str_cat.h"

namespace vasl {

absl::StatusOr<std::optional<store::OperationRecord>> FindCommitted(
    const store::ProjectStore& store, const store::OperationRecord& asked) {
  if (absl::Status bad = store::ValidateRequestId(asked.request_id); !bad.ok()) return bad;
  absl::StatusOr<std::optional<store::OperationRecord>> found =
      store.FindOperation(asked.request_id);
  if (!found.ok() || !*found || asked.kind.empty()) return found;
  const store::OperationRecord& done = **found;
  if (done.kind != asked.kind || done.subject != asked.subject) {
    return absl::FailedPreconditionError(absl::StrCat(
        "request id \"", asked.request_id, "\" was used for ", done.kind, " \"", done.subject,
        "\" (version ", done.version, "), not for ", asked.kind, " \"", asked.subject,
        "\": a new change needs a new request id"));
  }
  return found;
}

absl::StatusOr<std::optional<IngestResult>> ReplayOperation(const store::ProjectStore& store,
                                                            const store::OperationRecord& op) {
  if (op.request_id.empty()) return std::optional<IngestResult>();
  absl::StatusOr<std::optional<store::OperationRecord>> done = FindCommitted(store, op);
  if (!done.ok()) return done.status();
  if (!*done) return std::optional<IngestResult>();
  IngestResult replayed;
  replayed.replayed = true;
  replayed.version = (*done)->version;
  replayed.scan_id = (*done)->scan_id;
  replayed.answer = (*done)->answer;
  return std::optional<IngestResult>(std::move(replayed));
}

absl::StatusOr<std::optional<reweight::ReweightResult>> ReplayReweight(
    const store::ProjectStore& store, const store::OperationRecord& op) {
  absl::StatusOr<std::optional<IngestResult>> done = ReplayOperation(store, op);
  if (!done.ok()) return done.status();
  if (!*done) return std::optional<reweight::ReweightResult>();
  reweight::ReweightResult replayed;
  replayed.version = (*done)->version;
  replayed.replayed = true;
  replayed.answer = std::move((*done)->answer);
  return std::optional<reweight::ReweightResult>(std::move(replayed));
}

std::string ReweightSubject(const std::string& profile, int32_t revision) {
  return absl::StrCat(profile.empty() ? "active" : profile, "@",
                      revision == 0 ? std::string("latest") : absl::StrCat(revision));
}

}  // namespace vasl

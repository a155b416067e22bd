#include "server/request_check.h"

#include <string>

#include "absl/strings/str_cat.h"

namespace vasl::server {
namespace {

using google::protobuf::FieldDescriptor;
using google::protobuf::Message;
using google::protobuf::Reflection;

absl::Status CheckText(const std::string& path, const std::string& text, size_t max_bytes) {
  if (text.size() > max_bytes) {
    return absl::InvalidArgumentError(absl::StrCat(
        "field ", path, " has ", text.size(), " bytes; at most ", max_bytes, " are accepted"));
  }
  for (unsigned char c : text) {
    if (c < 0x20 || c == 0x7f) {
      return absl::InvalidArgumentError(absl::StrCat(
          "field ", path, " has a control character (byte ", int(c), "); use printable text"));
    }
  }
  return absl::OkStatus();
}

absl::Status Walk(const Message& m, const std::string& prefix, int depth) {
  if (depth > 8) return absl::OkStatus();  // our messages nest 3 deep; recursion is bounded
  const Reflection* r = m.GetReflection();
  std::vector<const FieldDescriptor*> fields;
  r->ListFields(m, &fields);  // set fields only
  for (const FieldDescriptor* f : fields) {
    const std::string path = prefix.empty() ? f->name() : absl::StrCat(prefix, ".", f->name());
    if (f->type() == FieldDescriptor::TYPE_STRING) {
      const size_t max = f->name() == "description" ? kDescriptionBytes : kTextBytes;
      if (f->is_repeated()) {
        for (int i = 0; i < r->FieldSize(m, f); ++i) {
          absl::Status s = CheckText(absl::StrCat(path, "[", i, "]"), r->GetRepeatedString(m, f, i), max);
          if (!s.ok()) return s;
        }
      } else if (absl::Status s = CheckText(path, r->GetString(m, f), max); !s.ok()) {
        return s;
      }
    } else if (f->type() == FieldDescriptor::TYPE_MESSAGE) {
      if (f->is_repeated()) {
        for (int i = 0; i < r->FieldSize(m, f); ++i) {
          absl::Status s = Walk(r->GetRepeatedMessage(m, f, i), absl::StrCat(path, "[", i, "]"), depth + 1);
          if (!s.ok()) return s;
        }
      } else if (absl::Status s = Walk(r->GetMessage(m, f), path, depth + 1); !s.ok()) {
        return s;
      }
    }
  }
  return absl::OkStatus();
}

}  // namespace

absl::Status CheckRequestStrings(const Message& request) { return Walk(request, "", 0); }

}  // namespace vasl::server

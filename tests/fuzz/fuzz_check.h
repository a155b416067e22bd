/// @file fuzz_check.h
/// @brief Invariant checks for the libFuzzer harnesses: a failed check prints what broke and
///        aborts, which libFuzzer reports as a crash with the input saved.
#pragma once

#include <cstdio>
#include <cstdlib>
#include <string>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"

/// Aborts with `message` (anything absl::StrCat takes) unless `cond` holds.
#define VASL_FUZZ_CHECK(cond, ...)                                                      \
  do {                                                                                  \
    if (!(cond)) {                                                                      \
      std::fprintf(stderr, "vasl fuzz check failed at %s:%d: %s: %s\n", __FILE__,      \
                   __LINE__, #cond, absl::StrCat(__VA_ARGS__).c_str());                 \
      std::abort();                                                                     \
    }                                                                                   \
  } while (0)

namespace vasl::fuzz {

/// A rejection of client input must be INVALID_ARGUMENT or RESOURCE_EXHAUSTED (engine.h:
/// INTERNAL only for bugs) and say why.
inline void CheckRejection(const absl::Status& status, const char* where) {
  VASL_FUZZ_CHECK(status.code() == absl::StatusCode::kInvalidArgument ||
                      status.code() == absl::StatusCode::kResourceExhausted,
                  where, " rejected input with an unexpected code: ", status.ToString());
  VASL_FUZZ_CHECK(!status.message().empty(), where, " rejected input without a message");
}

}  // namespace vasl::fuzz

/// @file request_check.h
/// @brief One check of every text field a client sends, before any handler reads it.
#pragma once

#include <google/protobuf/message.h>

#include "absl/status/status.h"

namespace vasl::server {

/// Bytes a text field of a request may hold: descriptions kDescriptionBytes, every other
/// string (names, ids, page tokens, labels) kTextBytes. Names have tighter limits of their own
/// (a project name 63, a scan id 128); this ceiling bounds what an error message, a log line or
/// a lookup can be handed before those checks run.
inline constexpr size_t kTextBytes = 1024;
inline constexpr size_t kDescriptionBytes = 4096;

/// INVALID_ARGUMENT when a string field of `request` (at any depth: nested messages, oneofs,
/// repeated fields) is longer than its ceiling or holds a control character (a byte below 0x20,
/// or 0x7f). The message names the field by its proto path and never echoes its content, so a
/// refusal cannot carry the client's bytes into a reply or a log.
absl::Status CheckRequestStrings(const google::protobuf::Message& request);

}  // namespace vasl::server

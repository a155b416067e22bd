/// @file frames.h
/// @brief The input format of fuzz_ingest_stream: a sequence of frames, each a LEB128 varint
///        length followed by that many bytes (one serialized vasl.v1.IngestScanRequest), as
///        protobuf's writeDelimitedTo writes them. Shared by the harness, its custom mutator and
///        the seed generator.
/// @details Decoding is total: a length running past the end of the input takes what is left,
///          and a truncated varint ends the sequence, so every byte string is a valid input.
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

namespace vasl::fuzz {

/// At most this many frames are decoded from one input (bounds the time of one run).
inline constexpr size_t kMaxFrames = 64;

/// Splits `bytes` into frames (views into `bytes`); at most kMaxFrames.
inline std::vector<std::string_view> DecodeFrames(std::string_view bytes) {
  std::vector<std::string_view> frames;
  size_t at = 0;
  while (at < bytes.size() && frames.size() < kMaxFrames) {
    uint64_t length = 0;
    int shift = 0;
    bool complete = false;
    while (at < bytes.size() && shift < 35) {
      const auto byte = static_cast<uint8_t>(bytes[at++]);
      length |= static_cast<uint64_t>(byte & 0x7f) << shift;
      shift += 7;
      if ((byte & 0x80) == 0) {
        complete = true;
        break;
      }
    }
    if (!complete) break;
    const size_t take = static_cast<size_t>(std::min<uint64_t>(length, bytes.size() - at));
    frames.push_back(bytes.substr(at, take));
    at += take;
  }
  return frames;
}

/// Appends one frame holding `payload` to `out`.
inline void AppendFrame(std::string_view payload, std::string* out) {
  uint64_t length = payload.size();
  do {
    uint8_t byte = length & 0x7f;
    length >>= 7;
    if (length != 0) byte |= 0x80;
    out->push_back(static_cast<char>(byte));
  } while (length != 0);
  out->append(payload);
}

/// Frames → one input.
inline std::string EncodeFrames(const std::vector<std::string>& frames) {
  std::string out;
  for (const std::string& frame : frames) AppendFrame(frame, &out);
  return out;
}

}  // namespace vasl::fuzz

/// @file proto_mutator.h
/// @brief A small structure-aware mutator for protobuf messages (protobuf reflection), so that
///        fuzz_ingest_stream changes one field of a request at a time instead of breaking its
///        wire encoding. Debian 12 has no libprotobuf-mutator; this is the part of it we need.
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <random>

#include <google/protobuf/message.h>

namespace vasl::fuzz {

/// Mutates bytes in place: (data, size, capacity) -> new size; libFuzzer's LLVMFuzzerMutate.
using BytesMutator = std::function<size_t(uint8_t* data, size_t size, size_t max_size)>;

/// Mutates one field of `message`, chosen uniformly among every field of every set
/// sub-message: a set integer, float or enum gets a nearby or boundary value (0, ±1, powers of
/// two and their neighbours, multiples of the point sizes 16 and 28, NaN, ±inf, extremes), a
/// bool flips, a string or bytes field is mutated by `mutate_bytes` with at most `max_growth`
/// more bytes (or resized by a multiple of 4), a repeated field gains, loses or swaps an
/// element, an unset field is set and a set message may be cleared.
void MutateMessage(google::protobuf::Message* message, std::minstd_rand& rng,
                   const BytesMutator& mutate_bytes, size_t max_growth);

}  // namespace vasl::fuzz

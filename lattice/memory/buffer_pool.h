/// @file buffer_pool.h
/// @brief Large float buffers kept for reuse, so that a buffer of the same size taken again
///        is neither mapped nor faulted in afresh.
/// @details glibc serves a buffer of megabytes from a fresh anonymous mapping and unmaps it
///          when it is freed; the next one faults in and the kernel clears every page again.
///          An ingest's revisits render two depth panoramas per older source, 8-32 MB each, one
///          after the other: on the corridor's 12th scan a third of a panorama's time went to
///          those faults and clears (perf, 2026-12-06), and a revisited camera's unpacked
///          panorama (geometry::LinearImage, 25 MB at 2048×1024) another such buffer, zeroed
///          on one thread before it was written (2026-12-07). Buffers given back here are
///          handed out again by the next take of at most their size; the pool holds a bounded
///          number of bytes (kBufferPoolBytes), so that a long-lived server keeps no more.
#pragma once

#include <cstddef>
#include <vector>

namespace vasl::memory {

/// Buffers below this are not kept (glibc's own bins serve them without faults).
inline constexpr std::size_t kPooledMinBytes = std::size_t(4) << 20;
/// Bytes of buffers the pool keeps at most: four full-size (4096×2048) depth panoramas.
inline constexpr std::size_t kBufferPoolBytes = std::size_t(128) << 20;

/// `n` copies of `value`, in the smallest kept buffer that holds `n` without wasting more than
/// half of it, or in a new one (advised for huge pages, AdviseHugePages) when none does.
std::vector<float> TakeFloats(std::size_t n, float value);

/// `n` values for a caller that writes every one before reading it: a kept buffer (as
/// TakeFloats chooses it) keeps whatever it held, so a take of at most the size given back
/// writes nothing; only values past that size, or a new buffer's, are zeroed.
std::vector<float> TakeFloatsForOverwrite(std::size_t n);

/// Gives `v`'s storage, and the values it holds, to the pool (it is left empty). Storage
/// below kPooledMinBytes is freed; when the pool would exceed kBufferPoolBytes its largest
/// buffers are freed first.
void GiveFloats(std::vector<float>&& v);

/// Bytes the pool holds now (for tests and diagnostics).
std::size_t PooledBytes();

/// Frees every buffer the pool holds.
void ReleasePooled();

}  // namespace vasl::memory

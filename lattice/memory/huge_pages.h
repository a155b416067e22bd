/// @file huge_pages.h
/// @brief Large buffers backed by transparent huge pages where the kernel offers them.
/// @details A buffer of tens of megabytes (a decoded panorama, a depth panorama, a fused
///          layer's columns) comes from glibc as a fresh anonymous mapping, so its first touch
///          takes one page fault per 4 KiB: on the realistic site half of a 4096×2048 PNG's
///          decode and a tenth of a fusion pass went to faults. With transparent huge pages in
///          "madvise" mode (this machine's) a buffer advised before its first touch faults once
///          per 2 MiB; in "always" mode the advice changes nothing, in "never" it is ignored.
#pragma once

#include <cstddef>
#include <vector>

namespace vasl::memory {

/// Buffers smaller than this are left alone: a huge page covers 2 MiB, and a mapping must span
/// a few of them for the advice to pay.
inline constexpr std::size_t kHugePageMinBytes = std::size_t(4) << 20;

/// Advises the kernel to back the whole pages within [p, p + bytes) with transparent huge
/// pages (madvise MADV_HUGEPAGE). Nothing below kHugePageMinBytes; a kernel without THP
/// refuses, which is not an error: the pages stay small.
void AdviseHugePages(void* p, std::size_t bytes);

/// `v` made `n` copies of `value`. When that takes at least kHugePageMinBytes and more than
/// `v` holds, its storage is allocated afresh and advised (AdviseHugePages) before the fill
/// touches it; otherwise it is std::vector::assign.
template <typename T>
void AssignOnHugePages(std::vector<T>& v, std::size_t n, const T& value = T()) {
  if (n * sizeof(T) >= kHugePageMinBytes && v.capacity() < n) {
    std::vector<T>().swap(v);
    v.reserve(n);
    AdviseHugePages(v.data(), n * sizeof(T));
  }
  v.assign(n, value);
}

}  // namespace vasl::memory

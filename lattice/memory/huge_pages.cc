#include "lattice/memory/huge_pages.h"

#include <sys/mman.h>
#include <unistd.h>

#include <cstdint>

namespace vasl::memory {

void AdviseHugePages(void* p, std::size_t bytes) {
  if (p == nullptr || bytes < kHugePageMinBytes) return;
  static const std::uintptr_t page = std::uintptr_t(sysconf(_SC_PAGESIZE));
  const std::uintptr_t begin = (std::uintptr_t(p) + page - 1) / page * page;
  const std::uintptr_t end = (std::uintptr_t(p) + bytes) / page * page;
  if (end <= begin) return;
  // EINVAL without THP in the kernel: the pages stay small, as they would have.
  (void)madvise(reinterpret_cast<void*>(begin), end - begin, MADV_HUGEPAGE);
}

}  // namespace vasl::memory

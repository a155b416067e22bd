#include "lattice/memory/isa.h"

#include <algorithm>
#include <atomic>

namespace vasl::memory {
namespace {

std::atomic<Isa> g_cap{Isa::kX86_64_V4};

}  // namespace

bool Supports(Isa isa) {
#if VASL_ISA_VARIANTS
  switch (isa) {
    case Isa::kBaseline: return true;
    case Isa::kAvx2: return __builtin_cpu_supports("avx2");
    case Isa::kX86_64_V4: return __builtin_cpu_supports("x86-64-v4");
  }
  return false;
#else
  return isa == Isa::kBaseline;
#endif
}

Isa WidestIsa() {
  static const Isa widest = Supports(Isa::kX86_64_V4) ? Isa::kX86_64_V4
                            : Supports(Isa::kAvx2)    ? Isa::kAvx2
                                                      : Isa::kBaseline;
  return std::min(widest, g_cap.load(std::memory_order_relaxed));
}

void SetIsaCap(Isa cap) { g_cap.store(cap, std::memory_order_relaxed); }

}  // namespace vasl::memory

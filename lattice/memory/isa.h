/// @file isa.h
/// @brief The instruction sets the hot kernels are compiled for, and which of them run here.
/// @details The §7 weight kernel (fusion/weight.cc) and the §5 depth panorama's splats
///          (ingest/visibility.cc) are compiled once per instruction set; each call takes the
///          widest variant this CPU runs. The build keeps -ffp-contract=off (no fused
///          multiply-add: GCC would otherwise contract a·b + c in the AVX2 and AVX-512
///          variants, even under -std=c++17), so every variant rounds every operation alike and
///          a project's weights and visibility are the same bits on every machine; tests
///          compare the variants through SetIsaCap.
#pragma once

#include <cstdint>

/// 1 where the wider variants are compiled (an x86-64 GCC build; clang, which builds
/// deploy/fuzz.sh's harnesses, and other architectures have the baseline alone), else 0.
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define VASL_ISA_VARIANTS 1
#else
#define VASL_ISA_VARIANTS 0
#endif

namespace vasl::memory {

enum class Isa : int8_t {
  kBaseline,   ///< x86-64 (SSE2), or whatever the compiler targets elsewhere
  kAvx2,       ///< x86-64 with AVX2
  kX86_64_V4,  ///< x86-64-v4: AVX-512 F, BW, CD, DQ, VL
};

/// Whether this CPU runs `isa`'s variants (kBaseline always; the others only in an x86-64 GCC
/// build, where they are compiled).
bool Supports(Isa isa);

/// The widest instruction set this CPU runs, no wider than the cap (SetIsaCap).
Isa WidestIsa();

/// Caps the variants every kernel takes from now on, process-wide (tests compare them; the
/// results are the same bits whatever the cap). kX86_64_V4: no cap, the default.
void SetIsaCap(Isa cap);

}  // namespace vasl::memory

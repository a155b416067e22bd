/// @file lanes.h
/// @brief Vectors of W lanes in GCC's vector extensions, for the kernels that compute W values
///        at once with each lane's operations in the scalar code's order (the build does not
///        fuse a·b + c), so that every lane keeps the scalar result's bits. A kernel is compiled
///        once per instruction set (memory/isa.h) with the width that set holds.
#pragma once

#include <cstdint>

namespace vasl::memory {

/// W doubles, W floats and W 64-bit integers (a compare of doubles gives its mask in these).
template <int W>
struct Lanes;
template <>
struct Lanes<1> {
  using Doubles = double;
  using Floats = float;
  using Int64s = int64_t;
};
template <>
struct Lanes<2> {
  using Doubles = double __attribute__((vector_size(16)));
  using Floats = float __attribute__((vector_size(8)));
  using Int64s = int64_t __attribute__((vector_size(16)));
};
template <>
struct Lanes<4> {
  using Doubles = double __attribute__((vector_size(32)));
  using Floats = float __attribute__((vector_size(16)));
  using Int64s = int64_t __attribute__((vector_size(32)));
};
template <>
struct Lanes<8> {
  using Doubles = double __attribute__((vector_size(64)));
  using Floats = float __attribute__((vector_size(32)));
  using Int64s = int64_t __attribute__((vector_size(64)));
};

}  // namespace vasl::memory

// TakeFloats / TakeFloatsForOverwrite / GiveFloats: the values promised, storage handed out again to a take it fits,
// small and oversized buffers not kept, and the pool's byte bound.
#include "lattice/memory/buffer_pool.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>

namespace vasl::memory {
namespace {

constexpr std::size_t kFloats = kPooledMinBytes / sizeof(float) * 2;  // 8 MB: kept

TEST(BufferPool, TakeFillsAndReusesGivenStorage) {
  ReleasePooled();
  std::vector<float> a = TakeFloats(kFloats, 1.5f);
  ASSERT_EQ(a.size(), kFloats);
  EXPECT_TRUE(std::all_of(a.begin(), a.end(), [](float v) { return v == 1.5f; }));
  const float* storage = a.data();
  a[7] = -3.0f;
  GiveFloats(std::move(a));
  EXPECT_TRUE(a.empty());
  EXPECT_EQ(PooledBytes(), kFloats * sizeof(float));
  // A take a little smaller gets the same storage, with every value written again.
  const float inf = std::numeric_limits<float>::infinity();
  std::vector<float> b = TakeFloats(kFloats - 100, inf);
  EXPECT_EQ(b.data(), storage);
  ASSERT_EQ(b.size(), kFloats - 100);
  EXPECT_TRUE(std::all_of(b.begin(), b.end(), [&](float v) { return v == inf; }));
  EXPECT_EQ(PooledBytes(), 0u);
  GiveFloats(std::move(b));
  // A take of less than half the kept buffer does not take it (it would waste over half).
  std::vector<float> c = TakeFloats(kFloats / 2 - 1, 0.0f);
  EXPECT_NE(c.data(), storage);
  EXPECT_EQ(PooledBytes(), kFloats * sizeof(float));
  ReleasePooled();
  EXPECT_EQ(PooledBytes(), 0u);
}

TEST(BufferPool, TakeForOverwriteWritesNothingWithinWhatWasGiven) {
  ReleasePooled();
  std::vector<float> a(kFloats, 2.0f);
  a[5] = -1.0f;
  const float* storage = a.data();
  GiveFloats(std::move(a));
  // Within the size given back, the buffer comes out as it went in (nothing is written).
  std::vector<float> b = TakeFloatsForOverwrite(kFloats - 10);
  EXPECT_EQ(b.data(), storage);
  ASSERT_EQ(b.size(), kFloats - 10);
  EXPECT_EQ(b[5], -1.0f);
  EXPECT_EQ(b[kFloats - 11], 2.0f);
  // Given back shorter, a longer take zeroes only the values past that.
  b.resize(100);
  GiveFloats(std::move(b));
  std::vector<float> c = TakeFloatsForOverwrite(kFloats);
  EXPECT_EQ(c.data(), storage);
  EXPECT_EQ(c[5], -1.0f);
  EXPECT_TRUE(std::all_of(c.begin() + 100, c.end(), [](float v) { return v == 0.0f; }));
  // None kept: a new buffer, zeroed.
  std::vector<float> d = TakeFloatsForOverwrite(kFloats);
  EXPECT_NE(d.data(), storage);
  EXPECT_TRUE(std::all_of(d.begin(), d.end(), [](float v) { return v == 0.0f; }));
  ReleasePooled();
}

TEST(BufferPool, SmallAndOversizedBuffersAreNotKept) {
  ReleasePooled();
  GiveFloats(std::vector<float>(1024, 0.0f));
  EXPECT_EQ(PooledBytes(), 0u);
  std::vector<float> huge;
  huge.reserve(kBufferPoolBytes / sizeof(float) + 1);
  GiveFloats(std::move(huge));
  EXPECT_EQ(PooledBytes(), 0u);
}

TEST(BufferPool, HoldsAtMostItsBoundDroppingTheLargestFirst) {
  ReleasePooled();
  const std::size_t n = kBufferPoolBytes / sizeof(float) / 4;  // four of n fill the pool
  for (std::size_t i = 0; i < 4; ++i) GiveFloats(std::vector<float>(n - 3 + i, 0.0f));
  EXPECT_EQ(PooledBytes(), (4 * n - 6) * sizeof(float));
  // No room for 8 MB more: the largest kept buffer (n floats) is dropped to make it.
  GiveFloats(std::vector<float>(kFloats, 0.0f));
  EXPECT_EQ(PooledBytes(), (3 * n - 6 + kFloats) * sizeof(float));
  EXPECT_LE(PooledBytes(), kBufferPoolBytes);
  // A take of n finds none that holds it; one of n - 1 gets the n - 1 kept.
  std::vector<float> t = TakeFloats(n - 1, 0.0f);
  EXPECT_EQ(t.capacity(), n - 1);
  std::vector<float> u = TakeFloats(n, 0.0f);
  EXPECT_EQ(PooledBytes(), (2 * n - 5 + kFloats) * sizeof(float));
  ReleasePooled();
}

}  // namespace
}  // namespace vasl::memory

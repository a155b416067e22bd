#include "lattice/memory/buffer_pool.h"

#include <algorithm>
#include <mutex>

#include "lattice/memory/huge_pages.h"

namespace vasl::memory {
namespace {

struct Pool {
  std::mutex mutex;
  std::vector<std::vector<float>> kept;  // by capacity, ascending
  std::size_t bytes = 0;
};

Pool& ThePool() {
  static Pool* pool = new Pool;  // never destroyed: buffers may come back during exit
  return *pool;
}

// The smallest kept buffer of capacity n to 2n (moved out of the pool), or a new one of
// capacity n advised for huge pages; its size is what it held, or 0.
std::vector<float> Reserved(std::size_t n) {
  std::vector<float> out;
  if (n * sizeof(float) >= kPooledMinBytes) {
    Pool& pool = ThePool();
    std::lock_guard<std::mutex> lock(pool.mutex);
    auto it = std::find_if(pool.kept.begin(), pool.kept.end(),
                           [n](const std::vector<float>& v) { return v.capacity() >= n; });
    if (it != pool.kept.end() && it->capacity() <= 2 * n) {
      out = std::move(*it);
      pool.bytes -= out.capacity() * sizeof(float);
      pool.kept.erase(it);
    }
  }
  if (out.capacity() < n) {
    out.reserve(n);
    AdviseHugePages(out.data(), n * sizeof(float));
  }
  return out;
}

}  // namespace

std::vector<float> TakeFloats(std::size_t n, float value) {
  std::vector<float> out = Reserved(n);
  out.assign(n, value);
  return out;
}

std::vector<float> TakeFloatsForOverwrite(std::size_t n) {
  std::vector<float> out = Reserved(n);
  out.resize(n);  // writes only the values past what the buffer held
  return out;
}

void GiveFloats(std::vector<float>&& v) {
  std::vector<float> mine = std::move(v);
  v.clear();
  const std::size_t b = mine.capacity() * sizeof(float);
  if (b < kPooledMinBytes || b > kBufferPoolBytes) return;  // freed on return
  std::vector<std::vector<float>> dropped;  // freed outside the lock
  {
    Pool& pool = ThePool();
    std::lock_guard<std::mutex> lock(pool.mutex);
    while (pool.bytes + b > kBufferPoolBytes && !pool.kept.empty()) {
      pool.bytes -= pool.kept.back().capacity() * sizeof(float);
      dropped.push_back(std::move(pool.kept.back()));
      pool.kept.pop_back();
    }
    auto at = std::lower_bound(pool.kept.begin(), pool.kept.end(), mine.capacity(),
                               [](const std::vector<float>& k, std::size_t c) {
                                 return k.capacity() < c;
                               });
    pool.bytes += b;
    pool.kept.insert(at, std::move(mine));
  }
}

std::size_t PooledBytes() {
  Pool& pool = ThePool();
  std::lock_guard<std::mutex> lock(pool.mutex);
  return pool.bytes;
}

void ReleasePooled() {
  std::vector<std::vector<float>> dropped;
  Pool& pool = ThePool();
  std::lock_guard<std::mutex> lock(pool.mutex);
  dropped.swap(pool.kept);
  pool.bytes = 0;
}

}  // namespace vasl::memory

/// @file worker_pool.cc
/// @brief Fixed thread pool for the engine's blocking calls.
#include "server/worker_pool.h"

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <exception>

#include <malloc.h>

#include "absl/strings/str_cat.h"

namespace vasl::server {
namespace {

/// A task that ran this long returns its freed heap to the kernel when it ends (Loop).
constexpr std::chrono::milliseconds kTrimAfter{100};

}  // namespace

WorkerPool::WorkerPool(int threads, size_t max_queued) : max_queued_(max_queued) {
  threads = std::max(1, threads);
  threads_.reserve(threads);
  for (int i = 0; i < threads; ++i) threads_.emplace_back([this] { Loop(); });
}

WorkerPool::~WorkerPool() { Stop(); }

absl::Status WorkerPool::Submit(std::function<void()> task) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (stopping_) return absl::UnavailableError("the server is shutting down; retry later");
    if (max_queued_ > 0 && tasks_.size() >= max_queued_) {
      return absl::ResourceExhaustedError(
          absl::StrCat("the server is busy: ", tasks_.size(),
                       " calls already wait for a worker (limit --max-queued-calls=", max_queued_,
                       "); retry later"));
    }
    tasks_.push_back(std::move(task));
  }
  cv_.notify_one();
  return absl::OkStatus();
}

void WorkerPool::Stop() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stopping_ = true;
  }
  cv_.notify_all();
  for (std::thread& t : threads_) {
    if (t.joinable()) t.join();
  }
}

void WorkerPool::Loop() {
  for (;;) {
    std::function<void()> task;
    {
      std::unique_lock<std::mutex> lock(mutex_);
      cv_.wait(lock, [this] { return stopping_ || !tasks_.empty(); });
      if (tasks_.empty()) return;  // stopping and drained
      task = std::move(tasks_.front());
      tasks_.pop_front();
    }
    // A task that throws must not end the process (std::terminate on a worker thread): the
    // RPC tasks catch their own errors and answer; this is the last line of defence.
    const auto started = std::chrono::steady_clock::now();
    try {
      task();
    } catch (const std::exception& e) {
      std::fprintf(stderr, "vasld: a worker task threw: %s\n", e.what());
    } catch (...) {
      std::fprintf(stderr, "vasld: a worker task threw a non-standard exception\n");
    }
#if defined(__GLIBC__)
    // After a long call, the heap it freed goes back to the kernel. An ingest, a reweight or a
    // large render frees hundreds of MB (decoded images, records, depth panoramas) across the
    // arenas of TBB's threads, which glibc keeps: an idle server would hold the peak of its
    // last call, and the next call's peak would come on top of what no arena could reuse.
    // Short calls skip it: a trim walks every free chunk of a fragmented heap (tens of ms).
    if (std::chrono::steady_clock::now() - started >= kTrimAfter) ::malloc_trim(0);
#endif
  }
}

}  // namespace vasl::server

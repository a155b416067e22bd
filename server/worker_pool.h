/// @file worker_pool.h
/// @brief A small fixed pool of threads that runs the engine's blocking, CPU-heavy calls off
///        gRPC's callback threads; reactors are finished from these threads.
/// @warning Thread-safe: Submit may be called from any thread until Stop.
#pragma once

#include <condition_variable>
#include <deque>
#include <functional>
#include <mutex>
#include <thread>
#include <vector>

#include "absl/status/status.h"

namespace vasl::server {

class WorkerPool {
 public:
  /// Starts `threads` workers (at least 1); at most `max_queued` tasks wait (0: no bound).
  explicit WorkerPool(int threads, size_t max_queued = 0);
  /// Stops (draining queued tasks) and joins.
  ~WorkerPool();
  WorkerPool(const WorkerPool&) = delete;
  WorkerPool& operator=(const WorkerPool&) = delete;

  /// Queues `task`. Does not run it and says why: RESOURCE_EXHAUSTED when `max_queued` tasks
  /// already wait, UNAVAILABLE after Stop.
  absl::Status Submit(std::function<void()> task);
  /// Runs every queued task, then joins the workers. Idempotent.
  void Stop();
  int size() const { return static_cast<int>(threads_.size()); }

 private:
  void Loop();

  std::mutex mutex_;
  std::condition_variable cv_;
  std::deque<std::function<void()>> tasks_;
  bool stopping_ = false;
  size_t max_queued_ = 0;
  std::vector<std::thread> threads_;
};

}  // namespace vasl::server

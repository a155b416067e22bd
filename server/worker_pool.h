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

namespace vasl::server {

class WorkerPool {
 public:
  /// Starts `threads` workers (at least 1).
  explicit WorkerPool(int threads);
  /// Stops (draining queued tasks) and joins.
  ~WorkerPool();
  WorkerPool(const WorkerPool&) = delete;
  WorkerPool& operator=(const WorkerPool&) = delete;

  /// Queues `task`; returns false (and does not run it) after Stop.
  bool Submit(std::function<void()> task);
  /// Runs every queued task, then joins the workers. Idempotent.
  void Stop();
  int size() const { return static_cast<int>(threads_.size()); }

 private:
  void Loop();

  std::mutex mutex_;
  std::condition_variable cv_;
  std::deque<std::function<void()>> tasks_;
  bool stopping_ = false;
  std::vector<std::thread> threads_;
};

}  // namespace vasl::server

#include "model/runtime/companion_thread.h"

#include <ATen/Parallel.h>
#include <ATen/ThreadLocalState.h>
#include <dlfcn.h>

#include <cstdio>
#include <cstdlib>
#include <utility>

namespace fd::model {

CompanionThread& CompanionThread::ForCurrentThread() {
  thread_local CompanionThread companion;
  return companion;
}

CompanionThread::CompanionThread() : thread_([this] { Loop(); }) {}

CompanionThread::~CompanionThread() {
  {
    std::unique_lock<std::mutex> lock(mu_);
    cv_.wait(lock, [this] { return !pending_ || done_; });
    stop_ = true;
  }
  cv_.notify_all();
  thread_.join();
}

void CompanionThread::Start(std::function<void()> work) {
  at::ThreadLocalState state;  // the caller's grad / inference mode
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (pending_) {
      std::fprintf(stderr, "CompanionThread::Start: work already pending\n");
      std::abort();
    }
    work_ = [state = std::move(state), work = std::move(work)] {
      at::ThreadLocalStateGuard guard(state);
      work();
    };
    pending_ = true;
    done_ = false;
    error_ = nullptr;
  }
  cv_.notify_all();
}

void CompanionThread::Wait() {
  std::exception_ptr error;
  {
    std::unique_lock<std::mutex> lock(mu_);
    if (!pending_) return;
    cv_.wait(lock, [this] { return done_; });
    pending_ = false;
    error = std::exchange(error_, nullptr);
  }
  if (error) std::rethrow_exception(error);
}

void CompanionThread::Loop() {
  // Each piece of work is one single-threaded half of a step. ATen first
  // initialises this thread's count (from the process-wide setting); then
  // OpenMP's per-thread count is set directly, because at::set_num_threads
  // would also change the process-wide default for threads started later.
  // (dlsym: OpenMP comes with LibTorch, not linked by this library itself.)
  (void)at::get_num_threads();
  using SetThreads = void (*)(int);
  if (auto set_threads = reinterpret_cast<SetThreads>(dlsym(RTLD_DEFAULT, "omp_set_num_threads"))) {
    set_threads(1);
  } else {
    at::set_num_threads(1);
  }
  std::unique_lock<std::mutex> lock(mu_);
  while (true) {
    cv_.wait(lock, [this] { return stop_ || (pending_ && !done_); });
    if (stop_) return;
    std::function<void()> work = std::move(work_);
    work_ = nullptr;
    lock.unlock();
    std::exception_ptr error;
    try {
      work();
    } catch (...) {
      error = std::current_exception();
    }
    work = nullptr;  // release what the work captured before reporting
    lock.lock();
    error_ = error;
    done_ = true;
    cv_.notify_all();
  }
}

CompanionWork::CompanionWork(CompanionThread& companion, std::function<void()> work)
    : companion_(companion) {
  companion_.Start(std::move(work));
}

CompanionWork::~CompanionWork() {
  if (joined_) return;
  try {
    companion_.Wait();
  } catch (...) {
    // The caller is already leaving with its own error.
  }
}

void CompanionWork::Join() {
  joined_ = true;
  companion_.Wait();
}

}  // namespace fd::model

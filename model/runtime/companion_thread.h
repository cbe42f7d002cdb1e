// CompanionThread: a second thread that one calling thread hands a piece of
// work to and later waits for, so that two independent halves of a
// denoising step run on two cores at once (FramePipeline: the UNet's down
// path beside the ControlNet, docs/BENCHMARKS.md, "The ControlNet beside the
// UNet").
//
// Why not a second intra-op thread: at the small shapes this project serves
// (a 16x16 latent, heads of 2-8 channels) most kernels are too short to
// split; OpenMP's fork/join per operator cost more than it saved (config B
// step 8.5 ms at 1 thread, 13.7 at 2). Two whole sub-networks on two threads,
// each single-threaded, synchronise twice per step instead of once per
// operator, and every operator runs exactly as at one thread (bitwise the
// same results).
//
// The work runs with the caller's LibTorch thread-local state (grad and
// inference mode, dispatch keys: at::ThreadLocalState) and at one intra-op
// thread; the project's own thread-local scopes (PromptKvScope,
// BatchInvariantScope) are not carried: the work sets up what it needs.
#ifndef FD_MODEL_RUNTIME_COMPANION_THREAD_H_
#define FD_MODEL_RUNTIME_COMPANION_THREAD_H_

#include <condition_variable>
#include <exception>
#include <functional>
#include <mutex>
#include <thread>

namespace fd::model {

class CompanionThread {
 public:
  // The calling thread's companion: started on first use, stopped and
  // joined when the calling thread exits. Thread-safety: each thread gets
  // its own; the reference must not leave the calling thread.
  static CompanionThread& ForCurrentThread();

  CompanionThread();
  // Waits for pending work, then stops the thread.
  ~CompanionThread();
  CompanionThread(const CompanionThread&) = delete;
  CompanionThread& operator=(const CompanionThread&) = delete;

  // Runs `work` on the companion and returns at once. Precondition: no work
  // is pending (Start / Wait alternate; checked, aborts otherwise).
  // Thread-safety: only from the owning thread.
  void Start(std::function<void()> work);
  // Blocks until the work has run; rethrows what it threw.
  void Wait();

 private:
  void Loop();

  std::mutex mu_;
  std::condition_variable cv_;
  std::function<void()> work_;  // guarded by mu_; set while pending
  bool pending_ = false;        // guarded by mu_: Start'ed, not yet Wait'ed
  bool done_ = false;           // guarded by mu_: the pending work has run
  bool stop_ = false;           // guarded by mu_
  std::exception_ptr error_;    // guarded by mu_
  std::thread thread_;          // last: starts after the members above exist
};

// RAII for one piece of companion work that borrows the caller's stack:
// starts it, and waits in the destructor if Join was not reached (an
// exception on the calling thread must not unwind what the work reads).
class CompanionWork {
 public:
  CompanionWork(CompanionThread& companion, std::function<void()> work);
  ~CompanionWork();
  CompanionWork(const CompanionWork&) = delete;
  CompanionWork& operator=(const CompanionWork&) = delete;

  // Waits; rethrows what the work threw.
  void Join();

 private:
  CompanionThread& companion_;
  bool joined_ = false;
};

}  // namespace fd::model

#endif  // FD_MODEL_RUNTIME_COMPANION_THREAD_H_

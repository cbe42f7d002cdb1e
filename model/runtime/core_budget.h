// CoreBudget: how many of the machine's cores the process's model calls
// occupy right now, so that a frame takes a second core only while one is
// idle (FramePipeline's ControlNet beside the UNet, ControlNetBeside::
// kWhenCoreFree).
//
// Why: on a 2-core server with two single-threaded batcher workers, a lone
// session leaves one core idle, and its frames can use it (the UNet's down
// path on a companion thread: docs/BENCHMARKS.md, "The ControlNet beside
// the UNet"); under load both workers compute and a companion would only
// oversubscribe the cores. Every FramePipeline call claims the cores it
// computes on for its duration; the companion is taken only if a core is
// left. The claims are what the pipelines say, not what the OS sees (other
// processes, the gRPC threads are not counted).
//
// Thread-safety: CoreBudget is thread-safe; a Claim belongs to one thread at
// a time.
#ifndef FD_MODEL_RUNTIME_CORE_BUDGET_H_
#define FD_MODEL_RUNTIME_CORE_BUDGET_H_

#include <atomic>
#include <optional>

namespace fd::model {

class CoreBudget {
 public:
  // The process's budget: the cores it may run on (sched_getaffinity, else
  // std::thread::hardware_concurrency, at least 1).
  static CoreBudget& Process();

  explicit CoreBudget(int cores);
  CoreBudget(const CoreBudget&) = delete;
  CoreBudget& operator=(const CoreBudget&) = delete;

  // Cores held while it lives (movable; releases them when destroyed).
  class Claim {
   public:
    Claim(Claim&& other) noexcept;
    Claim& operator=(Claim&& other) noexcept;
    Claim(const Claim&) = delete;
    Claim& operator=(const Claim&) = delete;
    ~Claim();

   private:
    friend class CoreBudget;
    Claim(CoreBudget* budget, int cores) : budget_(budget), cores_(cores) {}
    void Release();
    CoreBudget* budget_;
    int cores_;
  };

  // Claims `cores` (>= 0) whether or not they are free: the calls that
  // compute anyway are counted, so that companions see them.
  Claim Take(int cores);
  // Claims `cores` only if that many are free; nullopt otherwise.
  std::optional<Claim> TryTake(int cores);

  int cores() const { return cores_; }
  int in_use() const { return in_use_.load(std::memory_order_relaxed); }

 private:
  const int cores_;
  std::atomic<int> in_use_{0};
};

}  // namespace fd::model

#endif  // FD_MODEL_RUNTIME_CORE_BUDGET_H_

// A FramePipelineInterface for scheduler tests: delegates to a real pipeline
// and lets a test pause a step (a hook runs on the worker thread before each
// Step call), inject a failure into a chosen Step call, and check that every
// finished item's latents are finite.
#ifndef FD_TESTS_TESTING_SCRIPTED_FRAME_PIPELINE_H_
#define FD_TESTS_TESTING_SCRIPTED_FRAME_PIPELINE_H_

#include <torch/torch.h>

#include <atomic>
#include <functional>
#include <memory>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "session/frame_pipeline_interface.h"

namespace fd::testing {

// Thread-safety: configure before handing it to a scheduler (the hook and
// the failure index are read by the worker thread); the counters are atomic.
class ScriptedFramePipeline final : public session::FramePipelineInterface {
 public:
  explicit ScriptedFramePipeline(std::shared_ptr<const session::FramePipelineInterface> inner)
      : inner_(std::move(inner)) {}

  // Called before Step call number `call` (0-based) with its batch size.
  std::function<void(int call, size_t batch)> before_step;
  // Step call number fail_step_call returns INTERNAL "injected failure"
  // without stepping (-1: never).
  int fail_step_call = -1;

  int step_calls() const { return step_calls_.load(); }
  int finished_items() const { return finished_items_.load(); }
  // Items whose final latents had a NaN or Inf.
  int non_finite_items() const { return non_finite_items_.load(); }

  absl::StatusOr<std::vector<model::FrameState>> Begin(
      absl::Span<const model::PipelineInput> items) const override {
    return inner_->Begin(items);
  }

  absl::Status Step(absl::Span<model::FrameState* const> states) const override {
    const int call = step_calls_.fetch_add(1);
    if (before_step) before_step(call, states.size());
    if (call == fail_step_call) return absl::InternalError("injected failure");
    return inner_->Step(states);
  }

  absl::StatusOr<std::vector<model::FrameOutput>> Finish(
      absl::Span<model::FrameState* const> states) const override {
    for (const model::FrameState* s : states) {
      if (!torch::isfinite(s->latents).all().item<bool>()) non_finite_items_.fetch_add(1);
    }
    finished_items_.fetch_add(static_cast<int>(states.size()));
    return inner_->Finish(states);
  }

 private:
  std::shared_ptr<const session::FramePipelineInterface> inner_;
  mutable std::atomic<int> step_calls_{0};
  mutable std::atomic<int> finished_items_{0};
  mutable std::atomic<int> non_finite_items_{0};
};

// A one-shot gate: Wait() blocks until Open(). For pausing the worker.
class Gate {
 public:
  void Open() {
    absl::MutexLock lock(&mu_);
    open_ = true;
  }
  void Wait() {
    absl::MutexLock lock(&mu_);
    mu_.Await(absl::Condition(&open_));
  }

 private:
  absl::Mutex mu_;
  bool open_ = false;
};

}  // namespace fd::testing

#endif  // FD_TESTS_TESTING_SCRIPTED_FRAME_PIPELINE_H_

// Noise schedulers with per-sample state, ported from diffusers v0.31.0:
//   UniPCMultistepScheduler      (schedulers/scheduling_unipc_multistep.py)
//   DPMSolverMultistepScheduler  (schedulers/scheduling_dpmsolver_multistep.py)
//   DDIMScheduler                (schedulers/scheduling_ddim.py, eta = 0)
//   EulerDiscreteScheduler       (schedulers/scheduling_euler_discrete.py, s_churn = 0)
//
// diffusers keeps the timesteps, the step counter and the multistep history
// inside the scheduler object, so one object serves one denoising loop. Here
// that mutable part lives in a SchedulerState per batch item, and the
// Scheduler itself only holds the immutable training tables. A batched Step()
// takes one state per item, so items of one batch may be at different steps,
// have different step counts, or have just started (step-level batching).
// Each item's result is bit-identical to stepping it alone: every operation is
// elementwise, with per-item coefficients.
//
// Numerics follow diffusers: the per-step scalars (alpha_t, sigma_t, lambda,
// h, UniPC's B(h) and rho) are evaluated in float32 in the order diffusers
// evaluates its 0-d float32 tensors; tensors are stepped in float32 (diffusers'
// DPM-Solver and Euler upcast the sample; here every type does) and the
// result is returned in the sample's dtype.
#ifndef FD_MODEL_SCHEDULERS_SCHEDULER_H_
#define FD_MODEL_SCHEDULERS_SCHEDULER_H_

#include <torch/types.h>

#include <cstdint>
#include <memory>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/types/span.h"
#include "model/schedulers/scheduler_settings.h"

namespace fd::model {

class Scheduler;

// The per-item part of a diffusers scheduler after `set_timesteps(n)`: its
// timesteps and sigmas, the step counter and the multistep history.
//
// Ownership: a value type (copyable; copies share nothing mutable). Tensors it
// holds live on the device of the samples it was stepped with.
// Thread-safety: none; one state belongs to one denoising loop.
class SchedulerState {
 public:
  SchedulerState() = default;

  int num_inference_steps() const { return static_cast<int>(timestep_values_.size()); }
  // Index of the next step; == num_inference_steps() when finished.
  int step_index() const { return step_index_; }
  bool finished() const { return step_index_ >= num_inference_steps(); }

  // `scheduler.timesteps` after set_timesteps: int64 [n] for UniPC, DPM-Solver
  // and DDIM; float32 [n] for Euler (it may hold fractional timesteps). CPU.
  const torch::Tensor& timesteps() const { return timesteps_; }
  // `scheduler.sigmas`: float32 [n + 1] for UniPC/DPM-Solver/Euler (last is the
  // final sigma); undefined for DDIM, which has no sigma table. CPU.
  const torch::Tensor& sigmas() const { return sigmas_; }
  // The timestep the next Step() integrates from. Requires !finished().
  double current_timestep() const { return timestep_values_[step_index_]; }

  // Multistep order used by the last Step() (UniPC/DPM-Solver: `this_order`;
  // 1 for DDIM/Euler); 0 before the first step.
  int last_order() const { return last_order_; }
  // UniPC: the sample the last predictor started from, i.e. the UniC-corrected
  // sample for steps >= 1 (diffusers' `last_sample`). Undefined otherwise.
  // Shape [1, ...].
  const torch::Tensor& last_sample() const { return last_sample_; }

 private:
  friend class Scheduler;

  const void* owner_ = nullptr;  // tables of the Scheduler that created it
  torch::Tensor timesteps_;
  torch::Tensor sigmas_;
  std::vector<double> timestep_values_;  // host copies for the per-step scalars
  std::vector<float> sigma_values_;
  int step_index_ = 0;
  int lower_order_nums_ = 0;
  int last_order_ = 0;
  // Converted model outputs of the last solver_order steps, oldest first
  // (diffusers' `model_outputs`); each [1, ...] float32.
  std::vector<torch::Tensor> model_outputs_;
  torch::Tensor last_sample_;  // UniPC
};

struct SchedulerStepOutput {
  // [N, ...] in the dtype of the sample passed to Step().
  torch::Tensor prev_sample;
  // [N, ...] float32: the model's x0 prediction at this step (UniPC/DPM-Solver
  // with data prediction: the converted model output diffusers stores in
  // `model_outputs[-1]`; DDIM/Euler: `pred_original_sample`).
  torch::Tensor pred_original_sample;
};

// Ownership: a cheap handle; copies share the immutable tables.
// Thread-safety: all const methods may be called concurrently (with distinct
// states).
class Scheduler {
 public:
  // Builds the training tables (betas, alphas_cumprod, sigmas) for `settings`.
  // Errors: INVALID_ARGUMENT for values diffusers rejects (unknown
  // beta_schedule/prediction_type/solver_type/..., num_train_timesteps < 1,
  // solver_order < 1); UNIMPLEMENTED for diffusers options not ported here
  // (thresholding, Karras/exponential/beta/Lu sigmas, SDE DPM-Solver variants,
  // learned variance, Euler continuous timesteps or log-linear interpolation).
  static absl::StatusOr<Scheduler> Create(const SchedulerSettings& settings);

  const SchedulerSettings& settings() const;
  SchedulerType type() const { return settings().type; }
  // Training tables, CPU float32 [num_train_timesteps].
  const torch::Tensor& betas() const;
  const torch::Tensor& alphas_cumprod() const;
  // ((1 - alphas_cumprod) / alphas_cumprod) ** 0.5, float32 [num_train_timesteps].
  const torch::Tensor& train_sigmas() const;

  // A fresh state after `set_timesteps(num_inference_steps)`.
  // Errors: INVALID_ARGUMENT when num_inference_steps < 1 or > the number of
  // training timesteps, or when the spacing yields timesteps outside
  // [0, num_train_timesteps) (e.g. a large steps_offset).
  absl::StatusOr<SchedulerState> NewState(int num_inference_steps) const;

  // `init_noise_sigma` (1 except for Euler, where it depends on the state's
  // sigmas and the spacing).
  double InitNoiseSigma(const SchedulerState& state) const;

  // `scale_model_input` for each item at its current step: the identity except
  // for Euler (sample / sqrt(sigma^2 + 1)). sample: [N, ...], one state per
  // item. Errors: INVALID_ARGUMENT (count/shape mismatch, foreign state),
  // FAILED_PRECONDITION (a finished state).
  absl::StatusOr<torch::Tensor> ScaleModelInput(absl::Span<const SchedulerState* const> states,
                                                const torch::Tensor& sample) const;

  // The current timestep of each item as float32 [N] (what the UNet's time
  // embedding consumes; integer timesteps are exact in float32). CPU.
  absl::StatusOr<torch::Tensor> CurrentTimesteps(
      absl::Span<const SchedulerState* const> states) const;

  // One `scheduler.step(model_output, t, sample)` for every item, each at its
  // own step index, advancing every state by one step.
  // model_output, sample: [N, ...] floating point, same shape and device;
  // states: N distinct states created by this scheduler.
  // Errors (no state is modified on error): INVALID_ARGUMENT (N mismatch,
  // shapes/devices differ, non-floating dtype, a null/duplicate/foreign state,
  // a state whose history has another shape), FAILED_PRECONDITION (a state
  // that has finished all its steps), INTERNAL (LibTorch failure).
  absl::StatusOr<SchedulerStepOutput> Step(absl::Span<SchedulerState* const> states,
                                           const torch::Tensor& model_output,
                                           const torch::Tensor& sample) const;

 private:
  struct Tables;
  struct ItemScalars;
  explicit Scheduler(std::shared_ptr<const Tables> tables) : tables_(std::move(tables)) {}

  absl::Status ValidateStates(absl::Span<const SchedulerState* const> states, int64_t batch) const;
  absl::StatusOr<SchedulerStepOutput> StepUniPC(absl::Span<SchedulerState* const> states,
                                                const torch::Tensor& model_output,
                                                const torch::Tensor& sample) const;
  absl::StatusOr<SchedulerStepOutput> StepDPMSolver(absl::Span<SchedulerState* const> states,
                                                    const torch::Tensor& model_output,
                                                    const torch::Tensor& sample) const;
  absl::StatusOr<SchedulerStepOutput> StepDDIM(absl::Span<SchedulerState* const> states,
                                               const torch::Tensor& model_output,
                                               const torch::Tensor& sample) const;
  absl::StatusOr<SchedulerStepOutput> StepEuler(absl::Span<SchedulerState* const> states,
                                                const torch::Tensor& model_output,
                                                const torch::Tensor& sample) const;

  // Ends a multistep (UniPC / DPM-Solver) step: advances each updated state
  // of `next` (warm-up order count, step index) and moves it into `states`,
  // so the caller's states change only once the whole step succeeded.
  static void CommitMultistepStates(std::vector<SchedulerState>& next,
                                    absl::Span<SchedulerState* const> states, int solver_order);

  std::shared_ptr<const Tables> tables_;
};

}  // namespace fd::model

#endif  // FD_MODEL_SCHEDULERS_SCHEDULER_H_

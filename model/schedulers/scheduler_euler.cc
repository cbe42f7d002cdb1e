// EulerDiscreteScheduler.step (diffusers v0.31.0,
// schedulers/scheduling_euler_discrete.py) with s_churn = 0 (no noise is
// added, gamma = 0, sigma_hat = sigma), for a batch of per-item states.
// The model input must be scaled with Scheduler::ScaleModelInput first.
#include <torch/torch.h>

#include <utility>

#include "model/schedulers/scheduler.h"
#include "model/schedulers/scheduler_internal.h"

namespace fd::model {

using scheduler_internal::PerItem;

absl::StatusOr<SchedulerStepOutput> Scheduler::StepEuler(absl::Span<SchedulerState* const> states,
                                                         const torch::Tensor& model_output,
                                                         const torch::Tensor& sample) const {
  const SchedulerSettings& s = tables_->settings;
  const int64_t batch = sample.size(0);
  std::vector<float> sigma_hat, dt, v_out, v_skip;
  for (int64_t i = 0; i < batch; ++i) {
    const SchedulerState& st = *states[i];
    const float sigma = st.sigma_values_[st.step_index_];
    const float hat = sigma * (0.0f + 1.0f);  // sigma * (gamma + 1), gamma = 0
    sigma_hat.push_back(hat);
    dt.push_back(st.sigma_values_[st.step_index_ + 1] - hat);
    // v_prediction: denoised = model_output * c_out + input * c_skip
    const float norm = std::sqrt(sigma * sigma + 1.0f);
    v_out.push_back(-sigma / norm);
    v_skip.push_back(sigma * sigma + 1.0f);
  }
  const torch::Tensor hat = PerItem(sigma_hat, sample);

  // 1. compute predicted original sample (x_0) from sigma-scaled predicted noise
  torch::Tensor pred_original_sample;
  if (s.prediction_type == "epsilon") {
    pred_original_sample = sample - hat * model_output;
  } else if (s.prediction_type == "sample") {
    pred_original_sample = model_output;
  } else {  // v_prediction
    pred_original_sample = model_output * PerItem(v_out, sample) + sample / PerItem(v_skip, sample);
  }
  // 2. Convert to an ODE derivative
  const torch::Tensor derivative = (sample - pred_original_sample) / hat;
  torch::Tensor prev_sample = sample + derivative * PerItem(dt, sample);

  for (int64_t i = 0; i < batch; ++i) {
    states[i]->last_order_ = 1;
    ++states[i]->step_index_;
  }
  return SchedulerStepOutput{prev_sample, pred_original_sample};
}

}  // namespace fd::model

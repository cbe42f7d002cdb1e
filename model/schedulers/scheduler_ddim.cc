// DDIMScheduler.step (diffusers v0.31.0, schedulers/scheduling_ddim.py) with
// eta = 0 (deterministic), for a batch of per-item states. Formula (12) of
// https://arxiv.org/pdf/2010.02502.pdf without the noise term.
#include <torch/torch.h>

#include <cmath>
#include <utility>

#include "model/schedulers/scheduler.h"
#include "model/schedulers/scheduler_internal.h"

namespace fd::model {

using scheduler_internal::PerItem;

absl::StatusOr<SchedulerStepOutput> Scheduler::StepDDIM(absl::Span<SchedulerState* const> states,
                                                        const torch::Tensor& model_output,
                                                        const torch::Tensor& sample) const {
  const SchedulerSettings& s = tables_->settings;
  const int64_t batch = sample.size(0);
  const std::vector<float>& ac = tables_->alphas_cumprod_values;

  // Per item: alpha_prod_t ** 0.5, beta_prod_t ** 0.5, alpha_prod_t_prev ** 0.5
  // and (1 - alpha_prod_t_prev - std_dev_t**2) ** 0.5 with std_dev_t = 0.
  std::vector<float> sqrt_alpha, sqrt_beta, sqrt_alpha_prev, sqrt_direction;
  for (int64_t i = 0; i < batch; ++i) {
    const SchedulerState& st = *states[i];
    const int64_t t = static_cast<int64_t>(st.timestep_values_[st.step_index_]);
    // 1. prev_timestep = t - T // num_inference_steps (diffusers' formula,
    //    whatever the spacing).
    const int64_t prev_t = t - s.num_train_timesteps / st.num_inference_steps();
    // 2. alphas, betas
    const float alpha_prod_t = ac[t];
    const float alpha_prod_t_prev = prev_t >= 0 ? ac[prev_t] : tables_->final_alpha_cumprod;
    const float beta_prod_t = 1.0f - alpha_prod_t;
    sqrt_alpha.push_back(std::sqrt(alpha_prod_t));
    sqrt_beta.push_back(std::sqrt(beta_prod_t));
    sqrt_alpha_prev.push_back(std::sqrt(alpha_prod_t_prev));
    sqrt_direction.push_back(std::sqrt(1.0f - alpha_prod_t_prev - 0.0f));
  }
  const torch::Tensor a = PerItem(sqrt_alpha, sample);
  const torch::Tensor b = PerItem(sqrt_beta, sample);

  // 3. predicted original sample and epsilon from the model output.
  torch::Tensor pred_original_sample;
  torch::Tensor pred_epsilon;
  if (s.prediction_type == "epsilon") {
    pred_original_sample = (sample - b * model_output) / a;
    pred_epsilon = model_output;
  } else if (s.prediction_type == "sample") {
    pred_original_sample = model_output;
    pred_epsilon = (sample - a * pred_original_sample) / b;
  } else {  // v_prediction
    pred_original_sample = a * sample - b * model_output;
    pred_epsilon = a * model_output + b * sample;
  }
  // 4. clip "predicted x_0" (epsilon is not recomputed, as in diffusers).
  if (s.clip_sample) {
    pred_original_sample = pred_original_sample.clamp(-s.clip_sample_range, s.clip_sample_range);
  }
  // 6./7. direction pointing to x_t and x_{t-1} without noise.
  const torch::Tensor direction = PerItem(sqrt_direction, sample) * pred_epsilon;
  torch::Tensor prev_sample = PerItem(sqrt_alpha_prev, sample) * pred_original_sample + direction;

  for (int64_t i = 0; i < batch; ++i) {
    states[i]->last_order_ = 1;
    ++states[i]->step_index_;
  }
  return SchedulerStepOutput{prev_sample, pred_original_sample};
}

}  // namespace fd::model

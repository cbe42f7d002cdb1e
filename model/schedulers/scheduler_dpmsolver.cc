// DPMSolverMultistepScheduler.step (diffusers v0.31.0,
// schedulers/scheduling_dpmsolver_multistep.py) for a batch of per-item
// states, along diffusers' own methods: convert_model_output, then the
// first/second/third-order multistep update (dpmsolver++ or dpmsolver; midpoint or heun). The SDE
// variants are rejected at construction.
#include <torch/torch.h>

#include <algorithm>
#include <cmath>
#include <functional>
#include <utility>

#include "model/schedulers/scheduler.h"
#include "model/schedulers/scheduler_internal.h"

namespace fd::model {
namespace {

using scheduler_internal::AlphaSigma;
using scheduler_internal::FromSigma;
using scheduler_internal::PerItem;

// Per-item scalars of one update. The update is
//   x_t = c_sample * sample - c0 * D0 [- or +] c1 * D1 [- c2 * D2]
// with D1 = inv_r0 * (m0 - m1) (order 2), or the order-3 combinations.
struct DpmCoefficients {
  float c_sample = 0;
  float c0 = 0;
  float c1 = 0;
  float c2 = 0;
  float inv_r0 = 0;
  float inv_r1 = 0;
  float r0_over_sum = 0;  // r0 / (r0 + r1)
  float inv_sum = 0;      // 1 / (r0 + r1)
};

// The order of this item's update (step(): lower_order_final and
// lower_order_second lower it near the end, "for numerical stability with a
// small number of steps"; lower_order_nums_ ramps it up at the start).
// `idx`: the step index, `n`: the number of steps, `lower_order_nums`: the
// state's count of lower-order steps taken so far.
int UpdateOrder(const SchedulerSettings& s, int idx, int n, int lower_order_nums) {
  const bool lower_order_final =
      idx == n - 1 &&
      (s.euler_at_final || (s.lower_order_final && n < 15) || s.final_sigmas_type == "zero");
  const bool lower_order_second = idx == n - 2 && s.lower_order_final && n < 15;
  if (s.solver_order == 1 || lower_order_nums < 1 || lower_order_final) return 1;
  if (s.solver_order == 2 || lower_order_nums < 2 || lower_order_second) return 2;
  return 3;
}

// convert_model_output: the data prediction x0 and the noise prediction
// epsilon of `out` for rows `x` with per-item alpha `a` and sigma `sg`
// ([B, 1, 1, 1] each).
struct ConvertedOutput {
  torch::Tensor x0;       // [B, C, h, w]
  torch::Tensor epsilon;  // [B, C, h, w]
};
ConvertedOutput ConvertModelOutput(const SchedulerSettings& s, const torch::Tensor& x,
                                   const torch::Tensor& out, const torch::Tensor& a,
                                   const torch::Tensor& sg) {
  if (s.prediction_type == "epsilon") return {(x - sg * out) / a, out};
  if (s.prediction_type == "sample") return {out, (x - a * out) / sg};
  return {a * x - sg * out, a * out + sg * x};  // v_prediction
}

// The scalars of one item's update of `order` (the first/second/third-order
// update functions' sigma_t, alpha_t, h, r0, r1 arithmetic), on float32
// values in diffusers' order of evaluation.
// `sig`: the state's sigmas, `idx`: its step index.
DpmCoefficients UpdateCoefficients(const SchedulerSettings& s, const std::vector<float>& sig,
                                   int idx, int order) {
  const bool plus_plus = s.algorithm_type == "dpmsolver++";
  const bool midpoint = s.solver_type == "midpoint";
  const AlphaSigma t = FromSigma(sig[idx + 1]);
  const AlphaSigma s0 = FromSigma(sig[idx]);
  const float h = t.lambda - s0.lambda;
  DpmCoefficients c;
  if (plus_plus) {
    c.c_sample = t.sigma / s0.sigma;
    c.c0 = t.alpha * (std::exp(-h) - 1.0f);
  } else {
    c.c_sample = t.alpha / s0.alpha;
    c.c0 = t.sigma * (std::exp(h) - 1.0f);
  }
  if (order < 2) return c;
  const AlphaSigma s1 = FromSigma(sig[idx - 1]);
  const float h_0 = s0.lambda - s1.lambda;
  const float r0 = h_0 / h;
  c.inv_r0 = 1.0f / r0;
  if (order == 2) {
    if (midpoint) {
      c.c1 = 0.5f * c.c0;
    } else if (plus_plus) {  // heun
      c.c1 = t.alpha * ((std::exp(-h) - 1.0f) / h + 1.0f);
    } else {
      c.c1 = t.sigma * ((std::exp(h) - 1.0f) / h - 1.0f);
    }
    return c;
  }
  const AlphaSigma s2 = FromSigma(sig[idx - 2]);
  const float h_1 = s1.lambda - s2.lambda;
  const float r1 = h_1 / h;
  c.inv_r1 = 1.0f / r1;
  c.r0_over_sum = r0 / (r0 + r1);
  c.inv_sum = 1.0f / (r0 + r1);
  if (plus_plus) {
    c.c1 = t.alpha * ((std::exp(-h) - 1.0f) / h + 1.0f);
    c.c2 = t.alpha * ((std::exp(-h) - 1.0f + h) / (h * h) - 0.5f);
  } else {
    c.c1 = t.sigma * ((std::exp(h) - 1.0f) / h - 1.0f);
    c.c2 = t.sigma * ((std::exp(h) - 1.0f - h) / (h * h) - 0.5f);
  }
  return c;
}

// The per-item coefficient columns of a group ([B, 1, 1, 1] each, on x's
// device) and the model-output history m0 (newest), m1, m2.
struct UpdateInputs {
  std::function<torch::Tensor(float DpmCoefficients::*)> column;
  torch::Tensor m0, m1, m2;  // [B, C, h, w]; m1 from order 2, m2 from order 3
};

// dpm_solver_first_order_update.
torch::Tensor FirstOrderUpdate(const UpdateInputs& in, const torch::Tensor& x) {
  return in.column(&DpmCoefficients::c_sample) * x - in.column(&DpmCoefficients::c0) * in.m0;
}

// multistep_dpm_solver_second_order_update (midpoint or heun).
torch::Tensor SecondOrderUpdate(const SchedulerSettings& s, const UpdateInputs& in,
                                const torch::Tensor& x) {
  const bool plus_plus = s.algorithm_type == "dpmsolver++";
  const bool midpoint = s.solver_type == "midpoint";
  const torch::Tensor d1 = in.column(&DpmCoefficients::inv_r0) * (in.m0 - in.m1);
  torch::Tensor x_t = FirstOrderUpdate(in, x);
  if (midpoint || !plus_plus) return x_t - in.column(&DpmCoefficients::c1) * d1;
  return x_t + in.column(&DpmCoefficients::c1) * d1;
}

// multistep_dpm_solver_third_order_update.
torch::Tensor ThirdOrderUpdate(const SchedulerSettings& s, const UpdateInputs& in,
                               const torch::Tensor& x) {
  const bool plus_plus = s.algorithm_type == "dpmsolver++";
  const torch::Tensor d1_0 = in.column(&DpmCoefficients::inv_r0) * (in.m0 - in.m1);
  const torch::Tensor d1_1 = in.column(&DpmCoefficients::inv_r1) * (in.m1 - in.m2);
  const torch::Tensor d1 = d1_0 + in.column(&DpmCoefficients::r0_over_sum) * (d1_0 - d1_1);
  const torch::Tensor d2 = in.column(&DpmCoefficients::inv_sum) * (d1_0 - d1_1);
  const torch::Tensor x_t = FirstOrderUpdate(in, x);
  if (plus_plus) {
    return x_t + in.column(&DpmCoefficients::c1) * d1 - in.column(&DpmCoefficients::c2) * d2;
  }
  return x_t - in.column(&DpmCoefficients::c1) * d1 - in.column(&DpmCoefficients::c2) * d2;
}

}  // namespace

// step(): items are grouped by the order of their update, and each group
// runs convert_model_output and its update as one batched computation.
absl::StatusOr<SchedulerStepOutput> Scheduler::StepDPMSolver(
    absl::Span<SchedulerState* const> states, const torch::Tensor& model_output,
    const torch::Tensor& sample) const {
  const SchedulerSettings& s = tables_->settings;
  const bool plus_plus = s.algorithm_type == "dpmsolver++";
  const int64_t batch = sample.size(0);

  std::vector<SchedulerState> next(batch);
  scheduler_internal::Groups<int> groups;  // keyed by the order of the update
  for (int64_t i = 0; i < batch; ++i) {
    const SchedulerState& st = *states[i];
    groups[UpdateOrder(s, st.step_index_, st.num_inference_steps(), st.lower_order_nums_)]
        .push_back(i);
    next[i] = *states[i];
  }

  torch::Tensor prev_sample = torch::empty_like(sample);
  torch::Tensor x0_out = torch::empty_like(sample);
  for (const auto& [order, items] : groups) {
    const torch::Tensor x = scheduler_internal::Rows(sample, items);  // [B, C, h, w]
    const torch::Tensor out = scheduler_internal::Rows(model_output, items);

    std::vector<float> alpha, sigma;
    for (int64_t i : items) {
      const SchedulerState& st = *states[i];
      const AlphaSigma as = FromSigma(st.sigma_values_[st.step_index_]);
      alpha.push_back(as.alpha);
      sigma.push_back(as.sigma);
    }
    const ConvertedOutput converted =
        ConvertModelOutput(s, x, out, PerItem(alpha, x), PerItem(sigma, x));
    const torch::Tensor& model_output_kept = plus_plus ? converted.x0 : converted.epsilon;
    for (size_t j = 0; j < items.size(); ++j) {
      SchedulerState& st = next[items[j]];
      st.model_outputs_.push_back(model_output_kept.narrow(0, j, 1).clone());
      if (static_cast<int>(st.model_outputs_.size()) > s.solver_order) {
        st.model_outputs_.erase(st.model_outputs_.begin());
      }
      st.last_order_ = order;
    }

    std::vector<DpmCoefficients> coefs;
    std::vector<torch::Tensor> m0_items, m1_items, m2_items;
    for (int64_t i : items) {
      const SchedulerState& st = next[i];
      coefs.push_back(UpdateCoefficients(s, st.sigma_values_, st.step_index_, order));
      const auto& hist = st.model_outputs_;
      m0_items.push_back(hist.back());
      if (order >= 2) m1_items.push_back(hist[hist.size() - 2]);
      if (order >= 3) m2_items.push_back(hist[hist.size() - 3]);
    }
    UpdateInputs in;
    in.column = [&](float DpmCoefficients::*member) {
      std::vector<float> v;
      for (const DpmCoefficients& c : coefs) v.push_back(c.*member);
      return PerItem(v, x);
    };
    in.m0 = torch::cat(m0_items, 0);
    if (order >= 2) in.m1 = torch::cat(m1_items, 0);
    if (order >= 3) in.m2 = torch::cat(m2_items, 0);
    const torch::Tensor x_t = order == 1   ? FirstOrderUpdate(in, x)
                              : order == 2 ? SecondOrderUpdate(s, in, x)
                                           : ThirdOrderUpdate(s, in, x);
    scheduler_internal::SetRows(prev_sample, items, x_t);
    scheduler_internal::SetRows(x0_out, items, converted.x0);
  }

  CommitMultistepStates(next, states, s.solver_order);
  return SchedulerStepOutput{prev_sample, x0_out};
}

}  // namespace fd::model

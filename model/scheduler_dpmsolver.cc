// DPMSolverMultistepScheduler.step (diffusers v0.31.0,
// schedulers/scheduling_dpmsolver_multistep.py) for a batch of per-item
// states: convert_model_output, then the first/second/third-order multistep
// update (dpmsolver++ or dpmsolver; midpoint or heun). The SDE variants are
// rejected at construction.
#include <torch/torch.h>

#include <algorithm>
#include <cmath>
#include <utility>

#include "model/scheduler.h"
#include "model/scheduler_internal.h"

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

}  // namespace

absl::StatusOr<SchedulerStepOutput> Scheduler::StepDPMSolver(
    absl::Span<SchedulerState* const> states, const torch::Tensor& model_output,
    const torch::Tensor& sample) const {
  const SchedulerSettings& s = tables_->settings;
  const bool plus_plus = s.algorithm_type == "dpmsolver++";
  const bool midpoint = s.solver_type == "midpoint";
  const int64_t batch = sample.size(0);

  std::vector<SchedulerState> next(batch);
  scheduler_internal::Groups<int> groups;  // keyed by the order of the update
  for (int64_t i = 0; i < batch; ++i) {
    const SchedulerState& st = *states[i];
    const int idx = st.step_index_;
    const int n = st.num_inference_steps();
    // "Improve numerical stability for small number of steps"
    const bool lower_order_final =
        idx == n - 1 &&
        (s.euler_at_final || (s.lower_order_final && n < 15) || s.final_sigmas_type == "zero");
    const bool lower_order_second = idx == n - 2 && s.lower_order_final && n < 15;
    int order;
    if (s.solver_order == 1 || st.lower_order_nums_ < 1 || lower_order_final) {
      order = 1;
    } else if (s.solver_order == 2 || st.lower_order_nums_ < 2 || lower_order_second) {
      order = 2;
    } else {
      order = 3;
    }
    groups[order].push_back(i);
    next[i] = st;
  }

  torch::Tensor prev_sample = torch::empty_like(sample);
  torch::Tensor x0_out = torch::empty_like(sample);
  for (const auto& [order, items] : groups) {
    const torch::Tensor x = scheduler_internal::Rows(sample, items);
    const torch::Tensor out = scheduler_internal::Rows(model_output, items);

    // convert_model_output: data prediction (dpmsolver++) or noise (dpmsolver).
    std::vector<float> alpha, sigma;
    for (int64_t i : items) {
      const SchedulerState& st = *states[i];
      const AlphaSigma as = FromSigma(st.sigma_values_[st.step_index_]);
      alpha.push_back(as.alpha);
      sigma.push_back(as.sigma);
    }
    const torch::Tensor a = PerItem(alpha, x);
    const torch::Tensor sg = PerItem(sigma, x);
    torch::Tensor x0;
    torch::Tensor epsilon;
    if (s.prediction_type == "epsilon") {
      x0 = (x - sg * out) / a;
      epsilon = out;
    } else if (s.prediction_type == "sample") {
      x0 = out;
      epsilon = (x - a * out) / sg;
    } else {  // v_prediction
      x0 = a * x - sg * out;
      epsilon = a * out + sg * x;
    }
    const torch::Tensor converted = plus_plus ? x0 : epsilon;
    for (size_t j = 0; j < items.size(); ++j) {
      SchedulerState& st = next[items[j]];
      st.model_outputs_.push_back(converted.narrow(0, j, 1).clone());
      if (static_cast<int>(st.model_outputs_.size()) > s.solver_order) {
        st.model_outputs_.erase(st.model_outputs_.begin());
      }
      st.last_order_ = order;
    }

    // Scalars, on 0-d float32 values in diffusers' order of evaluation.
    std::vector<DpmCoefficients> coefs;
    std::vector<torch::Tensor> m0_items, m1_items, m2_items;
    for (int64_t i : items) {
      const SchedulerState& st = next[i];
      const int idx = st.step_index_;
      const std::vector<float>& sig = st.sigma_values_;
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
      if (order >= 2) {
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
        } else {
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
        }
      }
      coefs.push_back(c);
      const auto& hist = st.model_outputs_;
      m0_items.push_back(hist.back());
      if (order >= 2) m1_items.push_back(hist[hist.size() - 2]);
      if (order >= 3) m2_items.push_back(hist[hist.size() - 3]);
    }
    auto column = [&](float DpmCoefficients::*member) {
      std::vector<float> v;
      for (const DpmCoefficients& c : coefs) v.push_back(c.*member);
      return PerItem(v, x);
    };

    const torch::Tensor m0 = torch::cat(m0_items, 0);
    torch::Tensor x_t;
    if (order == 1) {
      // dpm_solver_first_order_update
      x_t = column(&DpmCoefficients::c_sample) * x - column(&DpmCoefficients::c0) * m0;
    } else if (order == 2) {
      // multistep_dpm_solver_second_order_update
      const torch::Tensor m1 = torch::cat(m1_items, 0);
      const torch::Tensor d1 = column(&DpmCoefficients::inv_r0) * (m0 - m1);
      x_t = column(&DpmCoefficients::c_sample) * x - column(&DpmCoefficients::c0) * m0;
      if (midpoint || !plus_plus) {
        x_t = x_t - column(&DpmCoefficients::c1) * d1;
      } else {
        x_t = x_t + column(&DpmCoefficients::c1) * d1;
      }
    } else {
      // multistep_dpm_solver_third_order_update
      const torch::Tensor m1 = torch::cat(m1_items, 0);
      const torch::Tensor m2 = torch::cat(m2_items, 0);
      const torch::Tensor d1_0 = column(&DpmCoefficients::inv_r0) * (m0 - m1);
      const torch::Tensor d1_1 = column(&DpmCoefficients::inv_r1) * (m1 - m2);
      const torch::Tensor d1 = d1_0 + column(&DpmCoefficients::r0_over_sum) * (d1_0 - d1_1);
      const torch::Tensor d2 = column(&DpmCoefficients::inv_sum) * (d1_0 - d1_1);
      x_t = column(&DpmCoefficients::c_sample) * x - column(&DpmCoefficients::c0) * m0;
      if (plus_plus) {
        x_t = x_t + column(&DpmCoefficients::c1) * d1 - column(&DpmCoefficients::c2) * d2;
      } else {
        x_t = x_t - column(&DpmCoefficients::c1) * d1 - column(&DpmCoefficients::c2) * d2;
      }
    }
    scheduler_internal::SetRows(prev_sample, items, x_t);
    scheduler_internal::SetRows(x0_out, items, x0);
  }

  CommitMultistepStates(next, states, s.solver_order);
  return SchedulerStepOutput{prev_sample, x0_out};
}

}  // namespace fd::model

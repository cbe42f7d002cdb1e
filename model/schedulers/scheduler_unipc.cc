// UniPCMultistepScheduler.step (diffusers v0.31.0,
// schedulers/scheduling_unipc_multistep.py) for a batch of per-item states,
// along diffusers' own methods: convert_model_output -> UniC corrector
// (multistep_uni_c_bh_update) -> history update -> UniP predictor
// (multistep_uni_p_bh_update).
// solver_p (another scheduler as predictor) is not supported.
#include <torch/torch.h>

#include <algorithm>
#include <cmath>
#include <tuple>
#include <utility>

#include "model/schedulers/scheduler.h"
#include "model/schedulers/scheduler_internal.h"

namespace fd::model {
namespace {

using scheduler_internal::AlphaSigma;
using scheduler_internal::FromSigma;
using scheduler_internal::PerItem;
using scheduler_internal::SolveSmall;

// The scalars of one B(h) update (predictor or corrector) for one item.
struct BhCoefficients {
  float sample_coef = 0;    // sigma_t / sigma_s0 (x0 form) or alpha_t / alpha_s0
  float m0_coef = 0;        // alpha_t * h_phi_1 (x0 form) or sigma_t * h_phi_1
  float res_coef = 0;       // alpha_t * B_h (x0 form) or sigma_t * B_h
  std::vector<float> rks;   // r_k for the order-1 older outputs (k = 1..order-1)
  std::vector<float> rhos;  // rhos_p (order - 1 values) or rhos_c (order values)
};

// Shared part of multistep_uni_p_bh_update / multistep_uni_c_bh_update:
// t_index/s0_index index `sigmas`; si_index[k-1] is the sigma index of the
// k-th older model output. `corrector` selects rhos_c (solve R b) over rhos_p.
BhCoefficients ComputeBh(const std::vector<float>& sigmas, int t_index, int s0_index,
                         const std::vector<int>& si_index, int order, bool predict_x0, bool bh1,
                         bool corrector) {
  const AlphaSigma t = FromSigma(sigmas[t_index]);
  const AlphaSigma s0 = FromSigma(sigmas[s0_index]);
  const float h = t.lambda - s0.lambda;

  BhCoefficients c;
  for (int k = 1; k < order; ++k) {
    const AlphaSigma si = FromSigma(sigmas[si_index[k - 1]]);
    c.rks.push_back((si.lambda - s0.lambda) / h);
  }
  std::vector<float> rks = c.rks;
  rks.push_back(1.0f);

  const float hh = predict_x0 ? -h : h;
  const float h_phi_1 = std::expm1(hh);  // h\phi_1(h) = e^h - 1
  float h_phi_k = h_phi_1 / hh - 1.0f;
  int64_t factorial_i = 1;
  const float b_h = bh1 ? hh : std::expm1(hh);

  // R[i-1][k] = rks[k]^(i-1), b[i-1] = h_phi_k * i! / B_h, for i = 1..order.
  std::vector<float> r(order * order);
  std::vector<float> b(order);
  for (int i = 1; i <= order; ++i) {
    for (int k = 0; k < order; ++k) {
      float p = 1.0f;
      for (int e = 0; e < i - 1; ++e) p *= rks[k];
      r[(i - 1) * order + k] = p;
    }
    b[i - 1] = h_phi_k * static_cast<float>(factorial_i) / b_h;
    factorial_i *= i + 1;
    h_phi_k = h_phi_k / hh - static_cast<float>(1.0 / static_cast<double>(factorial_i));
  }

  if (corrector) {
    // "for order 1, we use a simplified version"
    c.rhos = order == 1 ? std::vector<float>{0.5f} : SolveSmall(r, b);
  } else if (order == 2) {
    // "for order 2, we use a simplified version"
    c.rhos = {0.5f};
  } else if (order > 2) {
    // rhos_p = solve(R[:-1, :-1], b[:-1]).
    const int m = order - 1;
    std::vector<float> rm(m * m);
    for (int i = 0; i < m; ++i) {
      for (int k = 0; k < m; ++k) rm[i * m + k] = r[i * order + k];
    }
    c.rhos = SolveSmall(rm, std::vector<float>(b.begin(), b.begin() + m));
  }

  if (predict_x0) {
    c.sample_coef = t.sigma / s0.sigma;
    c.m0_coef = t.alpha * h_phi_1;
    c.res_coef = t.alpha * b_h;
  } else {
    c.sample_coef = t.alpha / s0.alpha;
    c.m0_coef = t.sigma * h_phi_1;
    c.res_coef = t.sigma * b_h;
    if (t.sigma == 0.0f) {
      // Final sigma 0 with noise prediction: h = +inf and diffusers computes
      // 0 * inf = NaN. sigma_t * (e^h - 1) -> alpha_t sigma_s0 / alpha_s0
      // (and sigma_t * h -> 0 for bh1) is the limit used here instead.
      c.m0_coef = t.alpha * s0.sigma / s0.alpha;
      c.res_coef = bh1 ? 0.0f : c.m0_coef;
    }
  }
  return c;
}

// Concatenates item tensors ([1, ...] each) of the given items.
torch::Tensor CatItems(const std::vector<torch::Tensor>& per_item) {
  return torch::cat(per_item, 0);
}

// D1_k = (m_k - m0) / r_k for k = 1..order-1, with per-item r_k.
std::vector<torch::Tensor> DifferenceTerms(const std::vector<torch::Tensor>& older,
                                           const torch::Tensor& m0,
                                           const std::vector<BhCoefficients>& coefs) {
  std::vector<torch::Tensor> d1s;
  for (size_t k = 0; k < older.size(); ++k) {
    std::vector<float> rk;
    for (const BhCoefficients& c : coefs) rk.push_back(c.rks[k]);
    d1s.push_back((older[k] - m0) / PerItem(rk, m0));
  }
  return d1s;
}

// einsum("k,bkc...->bc...", rhos, D1s) with per-item rhos (the first
// d1s.size() entries of each item's rhos).
torch::Tensor WeightedSum(const std::vector<torch::Tensor>& d1s,
                          const std::vector<BhCoefficients>& coefs) {
  torch::Tensor sum;
  for (size_t k = 0; k < d1s.size(); ++k) {
    std::vector<float> rho;
    for (const BhCoefficients& c : coefs) rho.push_back(c.rhos[k]);
    torch::Tensor term = PerItem(rho, d1s[k]) * d1s[k];
    sum = sum.defined() ? sum + term : term;
  }
  return sum;
}

std::vector<float> Column(const std::vector<BhCoefficients>& coefs, float BhCoefficients::*member) {
  std::vector<float> v;
  for (const BhCoefficients& c : coefs) v.push_back(c.*member);
  return v;
}

// convert_model_output: the reported x0 prediction and what enters the
// history (x0 with predict_x0, else the noise prediction), for rows `x` with
// per-item alpha `a` and sigma `sg` ([B, 1, 1, 1] each).
struct ConvertedOutput {
  torch::Tensor x0;         // [B, C, h, w]
  torch::Tensor converted;  // [B, C, h, w]
};
ConvertedOutput ConvertModelOutput(const SchedulerSettings& s, const torch::Tensor& x,
                                   const torch::Tensor& eps, const torch::Tensor& a,
                                   const torch::Tensor& sg) {
  const bool predict_x0 = s.predict_x0;
  if (s.prediction_type == "epsilon") {
    torch::Tensor x0 = (x - sg * eps) / a;
    return {x0, predict_x0 ? x0 : eps};
  }
  if (s.prediction_type == "sample") return {eps, predict_x0 ? eps : (x - a * eps) / sg};
  torch::Tensor x0 = a * x - sg * eps;  // v_prediction
  return {x0, predict_x0 ? x0 : a * eps + sg * x};
}

// What one item contributes to a B(h) update: its sigmas and step index, its
// model-output history (oldest first) and its last (corrected) sample.
struct ItemHistory {
  const std::vector<float>* sigmas = nullptr;
  int step_index = 0;
  const std::vector<torch::Tensor>* outputs = nullptr;  // [1, C, h, w] each
  torch::Tensor last_sample;                            // [1, C, h, w]
};

// A group's inputs of one B(h) update of order `p`, batched over its items.
struct BhInputs {
  std::vector<BhCoefficients> coefs;  // per item
  torch::Tensor m0;                   // [B, C, h, w], the newest history entry
  std::vector<torch::Tensor> older;   // p - 1 entries [B, C, h, w], newer first
  torch::Tensor last_sample;          // [B, C, h, w]; corrector only
};

// Gathers the inputs of the corrector (the update from step_index - 1 to
// step_index, whose older outputs are at step_index - (k + 1)) or of the
// predictor (step_index to step_index + 1, older outputs at step_index - k).
BhInputs GatherBh(const std::vector<ItemHistory>& items, int p, bool corrector, bool predict_x0,
                  bool bh1) {
  BhInputs in;
  std::vector<torch::Tensor> m0_items, last_items;
  std::vector<std::vector<torch::Tensor>> older_items(p - 1);
  for (const ItemHistory& item : items) {
    const int idx = item.step_index;
    const int t_index = corrector ? idx : idx + 1;
    const int s0_index = corrector ? idx - 1 : idx;
    std::vector<int> si;
    for (int k = 1; k < p; ++k) si.push_back(corrector ? idx - (k + 1) : idx - k);
    in.coefs.push_back(
        ComputeBh(*item.sigmas, t_index, s0_index, si, p, predict_x0, bh1, corrector));
    const std::vector<torch::Tensor>& hist = *item.outputs;
    m0_items.push_back(hist.back());
    for (int k = 1; k < p; ++k) older_items[k - 1].push_back(hist[hist.size() - 1 - k]);
    if (corrector) last_items.push_back(item.last_sample);
  }
  in.m0 = CatItems(m0_items);
  for (const auto& o : older_items) in.older.push_back(CatItems(o));
  if (corrector) in.last_sample = CatItems(last_items);
  return in;
}

// multistep_uni_c_bh_update: the incoming sample `x` corrected with this
// step's converted model output. Returns [B, C, h, w].
torch::Tensor MultistepUniCBhUpdate(const BhInputs& in, const torch::Tensor& converted,
                                    const torch::Tensor& x) {
  const std::vector<torch::Tensor> d1s = DifferenceTerms(in.older, in.m0, in.coefs);
  torch::Tensor x_t = PerItem(Column(in.coefs, &BhCoefficients::sample_coef), x) * in.last_sample -
                      PerItem(Column(in.coefs, &BhCoefficients::m0_coef), x) * in.m0;
  const torch::Tensor d1_t = converted - in.m0;
  std::vector<float> rho_last;
  for (const BhCoefficients& c : in.coefs) rho_last.push_back(c.rhos.back());
  torch::Tensor correction = PerItem(rho_last, x) * d1_t;
  if (!d1s.empty()) correction = WeightedSum(d1s, in.coefs) + correction;
  return x_t - PerItem(Column(in.coefs, &BhCoefficients::res_coef), x) * correction;
}

// multistep_uni_p_bh_update: the sample at the next timestep predicted from
// `x` with order `p`. Returns [B, C, h, w].
torch::Tensor MultistepUniPBhUpdate(const BhInputs& in, const torch::Tensor& x, int p) {
  torch::Tensor x_t = PerItem(Column(in.coefs, &BhCoefficients::sample_coef), x) * x -
                      PerItem(Column(in.coefs, &BhCoefficients::m0_coef), x) * in.m0;
  if (p > 1) {
    const torch::Tensor pred_res =
        WeightedSum(DifferenceTerms(in.older, in.m0, in.coefs), in.coefs);
    x_t = x_t - PerItem(Column(in.coefs, &BhCoefficients::res_coef), x) * pred_res;
  }
  // (Order 1: diffusers subtracts alpha_t * B_h * 0, which is NaN for bh1 at
  // a final sigma of 0 (B_h = -inf); the term is zero and is skipped here.)
  return x_t;
}

struct PathKey {
  int corrector_order;  // 0: no corrector
  int order;            // predictor order (this_order)
  bool operator<(const PathKey& o) const {
    return std::tie(corrector_order, order) < std::tie(o.corrector_order, o.order);
  }
};

}  // namespace

// step(): items are grouped by their path (corrector order, predictor
// order); each group runs convert_model_output -> UniC -> history update ->
// UniP as one batched computation.
absl::StatusOr<SchedulerStepOutput> Scheduler::StepUniPC(absl::Span<SchedulerState* const> states,
                                                         const torch::Tensor& model_output,
                                                         const torch::Tensor& sample) const {
  const SchedulerSettings& s = tables_->settings;
  const bool predict_x0 = s.predict_x0;
  const bool bh1 = s.solver_type == "bh1";
  const int64_t batch = sample.size(0);

  // Decide every item's path before touching any state.
  std::vector<SchedulerState> next(batch);
  scheduler_internal::Groups<PathKey> groups;
  for (int64_t i = 0; i < batch; ++i) {
    const SchedulerState& st = *states[i];
    const int idx = st.step_index_;
    const bool corrector_disabled =
        std::find(s.disable_corrector.begin(), s.disable_corrector.end(), idx - 1) !=
        s.disable_corrector.end();
    const bool use_corrector = idx > 0 && !corrector_disabled && st.last_sample_.defined();
    int order = s.solver_order;
    if (s.lower_order_final) order = std::min(order, st.num_inference_steps() - idx);
    order = std::min(order, st.lower_order_nums_ + 1);  // warmup for multistep
    groups[{use_corrector ? st.last_order_ : 0, order}].push_back(i);
    next[i] = st;
  }
  auto history = [](const SchedulerState& st) {
    return ItemHistory{&st.sigma_values_, st.step_index_, &st.model_outputs_, st.last_sample_};
  };

  torch::Tensor prev_sample = torch::empty_like(sample);
  torch::Tensor x0_out = torch::empty_like(sample);
  for (const auto& [key, items] : groups) {
    torch::Tensor x = scheduler_internal::Rows(sample, items);  // [B, C, h, w]
    const torch::Tensor eps = scheduler_internal::Rows(model_output, items);

    // convert_model_output (with the incoming, uncorrected sample).
    std::vector<float> alpha, sigma;
    for (int64_t i : items) {
      const SchedulerState& st = *states[i];
      const AlphaSigma as = FromSigma(st.sigma_values_[st.step_index_]);
      alpha.push_back(as.alpha);
      sigma.push_back(as.sigma);
    }
    const ConvertedOutput out = ConvertModelOutput(s, x, eps, PerItem(alpha, x), PerItem(sigma, x));

    // UniC: correct the incoming sample with this step's model output.
    if (key.corrector_order > 0) {
      std::vector<ItemHistory> incoming;
      for (int64_t i : items) incoming.push_back(history(*states[i]));
      const BhInputs in =
          GatherBh(incoming, key.corrector_order, /*corrector=*/true, predict_x0, bh1);
      x = MultistepUniCBhUpdate(in, out.converted, x);
    }

    // History update: model_outputs keeps the last solver_order outputs.
    for (size_t j = 0; j < items.size(); ++j) {
      SchedulerState& st = next[items[j]];
      st.model_outputs_.push_back(out.converted.narrow(0, j, 1).clone());
      if (static_cast<int>(st.model_outputs_.size()) > s.solver_order) {
        st.model_outputs_.erase(st.model_outputs_.begin());
      }
      st.last_sample_ = x.narrow(0, j, 1).clone();
      st.last_order_ = key.order;
    }

    // UniP: predict the sample at the next timestep.
    std::vector<ItemHistory> updated;
    for (int64_t i : items) updated.push_back(history(next[i]));
    const BhInputs in = GatherBh(updated, key.order, /*corrector=*/false, predict_x0, bh1);
    scheduler_internal::SetRows(prev_sample, items, MultistepUniPBhUpdate(in, x, key.order));
    scheduler_internal::SetRows(x0_out, items, out.x0);
  }

  CommitMultistepStates(next, states, s.solver_order);
  return SchedulerStepOutput{prev_sample, x0_out};
}

}  // namespace fd::model

// Internals shared by the scheduler implementation files (scheduler*.cc).
// Not part of the public API.
#ifndef FD_MODEL_SCHEDULERS_SCHEDULER_INTERNAL_H_
#define FD_MODEL_SCHEDULERS_SCHEDULER_INTERNAL_H_

#include <torch/torch.h>

#include <cmath>
#include <cstdint>
#include <map>
#include <vector>

#include "model/runtime/device_transfer.h"
#include "model/schedulers/scheduler.h"

namespace fd::model {

struct Scheduler::Tables {
  SchedulerSettings settings;
  TimestepSpacing spacing = TimestepSpacing::kLinspace;
  torch::Tensor betas;           // float32 [T]
  torch::Tensor alphas_cumprod;  // float32 [T]
  torch::Tensor train_sigmas;    // float32 [T]
  std::vector<float> alphas_cumprod_values;
  std::vector<float> train_sigma_values;
  float final_alpha_cumprod = 1.0f;  // DDIM
};

namespace scheduler_internal {

// diffusers' `_sigma_to_alpha_sigma_t` plus the log-SNR, on 0-d float32
// tensors: alpha = 1 / (sigma**2 + 1) ** 0.5, sigma_t = sigma * alpha,
// lambda = log(alpha) - log(sigma_t) (+inf for the final sigma 0).
struct AlphaSigma {
  float alpha;
  float sigma;
  float lambda;
};
inline AlphaSigma FromSigma(float sigma) {
  AlphaSigma out;
  out.alpha = 1.0f / std::sqrt(sigma * sigma + 1.0f);
  out.sigma = sigma * out.alpha;
  out.lambda = std::log(out.alpha) - std::log(out.sigma);
  return out;
}

// Per-item scalars as a float32 tensor [G, 1, ..., 1] broadcastable against
// `like` ([G, ...]) and on its device.
inline torch::Tensor PerItem(const std::vector<float>& values, const torch::Tensor& like) {
  std::vector<int64_t> shape(like.dim(), 1);
  shape[0] = static_cast<int64_t>(values.size());
  // Without a host sync on CUDA (called once per step and coefficient).
  return ToDeviceAsync(torch::tensor(values, torch::dtype(torch::kFloat32)).view(shape),
                       like.device());
}

// Items of a batch that take the same code path (e.g. the same solver order),
// keyed by that path. Each group is stepped with one set of tensor ops on
// per-item coefficients; since every op is elementwise, an item's result does
// not depend on which other items share its group.
template <typename Key>
using Groups = std::map<Key, std::vector<int64_t>>;

// Rows `items` of x ([N, ...]); x itself when items is 0..N-1.
inline torch::Tensor Rows(const torch::Tensor& x, const std::vector<int64_t>& items) {
  bool identity = static_cast<int64_t>(items.size()) == x.size(0);
  for (size_t i = 0; identity && i < items.size(); ++i) identity = items[i] == int64_t(i);
  if (identity) return x;
  return x.index_select(0, torch::tensor(items, torch::kLong).to(x.device()));
}

// out[items] = values.
inline void SetRows(torch::Tensor& out, const std::vector<int64_t>& items,
                    const torch::Tensor& values) {
  if (static_cast<int64_t>(items.size()) == out.size(0)) {
    bool identity = true;
    for (size_t i = 0; identity && i < items.size(); ++i) identity = items[i] == int64_t(i);
    if (identity) {
      out.copy_(values);
      return;
    }
  }
  out.index_copy_(0, torch::tensor(items, torch::kLong).to(out.device()), values);
}

// Solves A x = b (n x n, row-major) in float32 by LU with partial pivoting,
// as torch.linalg.solve (LAPACK sgesv) does for UniPC's small systems.
std::vector<float> SolveSmall(std::vector<float> a, std::vector<float> b);

}  // namespace scheduler_internal
}  // namespace fd::model

#endif  // FD_MODEL_SCHEDULERS_SCHEDULER_INTERNAL_H_

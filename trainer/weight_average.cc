#include "trainer/weight_average.h"

#include <torch/torch.h>

#include <algorithm>
#include <utility>

#include "absl/strings/str_cat.h"

namespace fd::trainer {

WeightAverage::WeightAverage(std::vector<torch::Tensor> params, double max_decay)
    : params_(std::move(params)), max_decay_(max_decay) {
  torch::NoGradGuard no_grad;
  average_.reserve(params_.size());
  for (const torch::Tensor& p : params_) average_.push_back(p.detach().clone());
}

double WeightAverage::DecayAt(int64_t step) const {
  if (step <= 1) return 0.0;
  const double n = static_cast<double>(step);
  return std::min(max_decay_, n / (9.0 + n));
}

void WeightAverage::Update(int64_t step) {
  torch::NoGradGuard no_grad;
  const double weight = 1.0 - DecayAt(step);
  // average += (1 - decay) * (param - average), EMAModel.step's update.
  for (size_t i = 0; i < params_.size(); ++i) average_[i].lerp_(params_[i].detach(), weight);
}

void WeightAverage::Swap() {
  torch::NoGradGuard no_grad;
  for (size_t i = 0; i < params_.size(); ++i) {
    torch::Tensor held = params_[i].detach().clone();
    params_[i].copy_(average_[i]);
    average_[i].copy_(held);
  }
}

std::map<std::string, torch::Tensor> WeightAverage::State() const {
  std::map<std::string, torch::Tensor> out;
  for (size_t i = 0; i < average_.size(); ++i) out[std::to_string(i)] = average_[i];
  return out;
}

absl::Status WeightAverage::Load(const std::map<std::string, torch::Tensor>& state) {
  if (state.size() != average_.size()) {
    return absl::InvalidArgumentError(absl::StrCat("the weight average holds ", state.size(),
                                                   " tensors, the stage trains ", average_.size()));
  }
  for (size_t i = 0; i < average_.size(); ++i) {
    const auto it = state.find(std::to_string(i));
    if (it == state.end() || it->second.sizes() != average_[i].sizes()) {
      return absl::InvalidArgumentError(
          absl::StrCat("weight average tensor ", i, " is missing or has another shape"));
    }
  }
  torch::NoGradGuard no_grad;
  for (size_t i = 0; i < average_.size(); ++i) {
    average_[i].copy_(state.at(std::to_string(i)));
  }
  return absl::OkStatus();
}

}  // namespace fd::trainer

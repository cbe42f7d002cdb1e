// An exponential moving average of the weights a stage trains (diffusers'
// training_utils.EMAModel without its power warm-up: `--use_ema` of the
// diffusers training scripts). After optimizer step n (counted from 1) the
// average moves towards the weights by 1 - decay(n), where
//   decay(1) = 0 (the average starts at the first step's weights),
//   decay(n) = min(max_decay, n / (9 + n))  (EMAModel's (1 + s) / (10 + s), s = n - 1),
// so early in a short stage the average spans about the last n / 9 steps and
// never more than 1 / (1 - max_decay). The authors train without one
// (training-reference §1.1); with batches of 4 the last weights carry the noise
// of the last few steps, which the average smooths out.
//
// Thread-safety: not thread-safe; used from the trainer's thread only.
#ifndef FD_TRAINER_WEIGHT_AVERAGE_H_
#define FD_TRAINER_WEIGHT_AVERAGE_H_

#include <torch/types.h>

#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include "absl/status/status.h"

namespace fd::trainer {

class WeightAverage {
 public:
  // Averages `params` (handles to the trained tensors, shared with their
  // networks: Update reads them, Swap writes them), starting from their
  // current values. max_decay in [0, 1).
  WeightAverage(std::vector<torch::Tensor> params, double max_decay);

  // The decay applied by the update after optimizer step `step` (from 1).
  double DecayAt(int64_t step) const;
  // Moves the average towards the parameters' current values; call once
  // after optimizer step `step` (from 1).
  void Update(int64_t step);
  // Exchanges the parameters' values with the average's: after one call the
  // networks hold the average, after a second the weights they had.
  void Swap();

  // The average's tensors by position ("0", "1", ...) for a checkpoint.
  std::map<std::string, torch::Tensor> State() const;
  // Restores State()'s output; INVALID_ARGUMENT (naming the tensor) when a
  // tensor is missing or has another shape than the parameter it averages.
  absl::Status Load(const std::map<std::string, torch::Tensor>& state);

  double max_decay() const { return max_decay_; }
  const std::vector<torch::Tensor>& average() const { return average_; }

 private:
  std::vector<torch::Tensor> params_;
  std::vector<torch::Tensor> average_;  // float32 masters' copies
  double max_decay_;
};

}  // namespace fd::trainer

#endif  // FD_TRAINER_WEIGHT_AVERAGE_H_

// Gradient checkpointing: PyTorch's torch.utils.checkpoint.checkpoint
// (use_reentrant=True, the variant diffusers v0.31.0 blocks call when
// `gradient_checkpointing` is set) for LibTorch C++, which has none.
//
// A checkpointed function keeps no intermediate activations for backward:
// only its inputs are saved; backward runs it again with grad enabled and
// back-propagates through the recomputed graph. Training then holds, per
// checkpointed block, its inputs instead of every activation inside it, at
// the price of a second forward of the block (`fd_trainer_bench
// --gradient_checkpointing 0,1` measures both per stage).
//
// As in PyTorch's reentrant variant, parameters used by the function get
// their gradients accumulated into `.grad` during the recomputation's
// backward (loss.backward() then sees them; torch::autograd::grad() with
// parameters as inputs does not), and every tensor that needs a gradient
// must be passed in `inputs`, not captured by the function. The function
// must be deterministic (the blocks checkpointed here use no dropout and no
// random numbers), so the recomputation equals the first forward.
#ifndef FD_MODEL_NETWORKS_GRADIENT_CHECKPOINT_H_
#define FD_MODEL_NETWORKS_GRADIENT_CHECKPOINT_H_

#include <torch/nn/module.h>
#include <torch/types.h>

#include <functional>
#include <vector>

namespace fd::model {

// The function to checkpoint: receives `inputs` (undefined ones stay
// undefined) and returns one tensor.
using CheckpointedFunction = std::function<torch::Tensor(const std::vector<torch::Tensor>&)>;

// Runs `function(inputs)` without storing its activations for backward
// when grad mode is on and a defined input requires a gradient; otherwise
// calls it directly (without such an input the parameters inside would get
// no gradient through a checkpoint). Returns its output: equal
// values, and equal gradients for the defined `inputs` and the parameters
// the function uses (up to the order of floating-point accumulation).
// Thread-safety: as the function; each call is independent.
// Throws what the function throws (LibTorch errors, c10::Error), like any
// module forward: model/ catches them at its public edges.
torch::Tensor Checkpoint(CheckpointedFunction function, const std::vector<torch::Tensor>& inputs);

// A module that checkpoints its sub-blocks while training when enabled
// (diffusers' `module.gradient_checkpointing`). The flag changes memory and
// time only, never results.
class GradientCheckpointable {
 public:
  virtual ~GradientCheckpointable() = default;
  void set_gradient_checkpointing(bool enabled) { gradient_checkpointing_ = enabled; }
  bool gradient_checkpointing() const { return gradient_checkpointing_; }

 protected:
  // Whether a forward should checkpoint now: enabled and grad mode on (no
  // recomputation in inference, under NoGradGuard or InferenceMode).
  bool ShouldCheckpoint() const;

 private:
  bool gradient_checkpointing_ = false;
};

// diffusers ModelMixin.enable_gradient_checkpointing /
// disable_gradient_checkpointing: sets the flag of `root` and every
// submodule that is GradientCheckpointable. Returns how many modules it
// set (0 when the network has none). Not thread-safe with a concurrent
// forward of the same network.
int SetGradientCheckpointing(torch::nn::Module& root, bool enabled);

}  // namespace fd::model

#endif  // FD_MODEL_NETWORKS_GRADIENT_CHECKPOINT_H_

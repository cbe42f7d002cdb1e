// What the network loaders (LoadUNet, LoadControlNet, LoadVae) do after
// strict loading (state_dict_loader.h): moving the model to its device/dtype.
#ifndef FD_MODEL_CHECKPOINT_CHECKPOINT_LOADING_H_
#define FD_MODEL_CHECKPOINT_CHECKPOINT_LOADING_H_

#include <torch/nn/module.h>
#include <torch/types.h>

#include "absl/status/status.h"

namespace fd::model {

// Moves `module` to `device` / `dtype` (float32, float16 or bfloat16) and
// switches it to eval mode. INVALID_ARGUMENT for another dtype, a CUDA
// device without CUDA, or float16 on the CPU with LibTorch 1.x (no Half CPU
// kernels); INTERNAL on torch errors.
absl::Status MoveModule(torch::nn::Module& module, torch::Device device, torch::Dtype dtype);

}  // namespace fd::model

#endif  // FD_MODEL_CHECKPOINT_CHECKPOINT_LOADING_H_

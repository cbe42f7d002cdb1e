// Device/dtype moves of loaded networks; see checkpoint_loading.h.
#include "model/checkpoint/checkpoint_loading.h"

#include <torch/cuda.h>
#include <torch/torch.h>
#include <torch/version.h>

#include "absl/strings/str_cat.h"
#include "base/status_macros.h"
#include "model/runtime/torch_call.h"

namespace fd::model {

absl::Status MoveModule(torch::nn::Module& module, torch::Device device, torch::Dtype dtype) {
  if (dtype != torch::kFloat32 && dtype != torch::kFloat16 && dtype != torch::kBFloat16) {
    return absl::InvalidArgumentError(absl::StrCat("unsupported model dtype ", c10::toString(dtype),
                                                   " (supported: float32, float16, bfloat16)"));
  }
#if TORCH_VERSION_MAJOR < 2
  // LibTorch 1.x has no Half CPU kernels for matmul/conv ("addmm_impl_cpu_"
  // not implemented for 'Half'): refuse at load time, not at the first step.
  if (device.is_cpu() && dtype == torch::kFloat16) {
    return absl::InvalidArgumentError(
        "float16 on the CPU is not supported by this LibTorch (1.x); use bfloat16 or float32 "
        "on the CPU, or float16 on CUDA");
  }
#endif
  if (device.is_cuda() && !torch::cuda::is_available()) {
    return absl::InvalidArgumentError(
        absl::StrCat("device ", device.str(), " requested but CUDA is not available"));
  }
  return TorchCall("MoveModule", [&]() -> absl::Status {
    module.to(device, dtype);
    module.eval();
    return absl::OkStatus();
  });
}

}  // namespace fd::model

// Host -> device copies that do not stall the host.
//
// A plain `t.to(cuda)` of a pageable CPU tensor waits for the copy, and so
// for every kernel queued before it: once per denoising step (timesteps)
// and per scheduler coefficient, that would synchronise the host with the
// GPU inside the step loop and leave the GPU idle while the next step's
// work is being issued. Copying from pinned (page-locked) memory with
// non_blocking=true queues the copy on the current stream instead; LibTorch's
// pinned host allocator keeps the staging block alive until the copy is done.
#ifndef FD_MODEL_RUNTIME_DEVICE_TRANSFER_H_
#define FD_MODEL_RUNTIME_DEVICE_TRANSFER_H_

#include <torch/types.h>

namespace fd::model {

// `host` on `device`. For a CPU tensor going to a CUDA device the copy is
// asynchronous (pinned staging); otherwise it is `host.to(device)`: on the
// CPU nothing changes, not even the result's bits. Thread-safety: as
// Tensor::to. Throws what LibTorch throws (callers wrap it in TorchCall).
inline torch::Tensor ToDeviceAsync(const torch::Tensor& host, const torch::Device& device) {
  if (device.is_cuda() && host.device().is_cpu()) {
    return host.pin_memory().to(device, /*non_blocking=*/true);
  }
  return host.to(device);
}

}  // namespace fd::model

#endif  // FD_MODEL_RUNTIME_DEVICE_TRANSFER_H_

// GroupNorm on channels-last inference tensors whose result does not depend
// on the number of intra-op threads or on the other items of a batch.
//
// LibTorch 1.13's channels-last GroupNorm kernel, on feature maps of 1024
// positions or more, gives each intra-op thread a share of the rows, sums the
// share into that thread's own buffer and then adds the buffers. So the
// moments, and every pixel after them, depend on how many threads ran: a
// [1, 32, 128, 128] map normalises up to 1.9e-5 apart at 1 and 2 threads
// (the VAE's outer levels, which run channels-last; conv2d_kernel.h), and in
// a batch the shares cut across items. A decode on a second free core
// (FramePipelineOptions::vae_on_free_core) then changed the frame, and a
// server whose calibration chose differently after a restart rendered other
// frames for the same seed. The NCHW kernel is invariant (one group per
// task) but converting to it and back cost 3-15x the norm. This kernel sums
// fixed blocks of rows, so each block's partial sums and their order are the
// same at any thread count and batch size.
#ifndef FD_MODEL_RUNTIME_GROUP_NORM_KERNEL_H_
#define FD_MODEL_RUNTIME_GROUP_NORM_KERNEL_H_

#include <torch/nn/modules/normalization.h>
#include <torch/types.h>

namespace fd::model {

// Whether GroupNormForward computes `x` with the invariant kernel: a 4-D
// float32 CPU tensor in channels-last memory format (and not also
// NCHW-contiguous), outside autograd. Thread-safe.
bool UseInvariantGroupNorm(const torch::Tensor& x);

// norm(x) ([N, C, H, W] -> same shape and memory format). Inputs that
// UseInvariantGroupNorm accepts take the invariant kernel (float sums of
// fixed 256-row blocks, added in double: equal to ATen's within float32
// rounding, bitwise the same at any thread count and for an item alone or
// in a batch); all others take torch::group_norm, as the module does. Throws c10::Error like the
// module on misfit inputs. Thread-safe for concurrent calls with the module's parameters unchanged.
torch::Tensor GroupNormForward(const torch::nn::GroupNormImpl& norm, const torch::Tensor& x);

}  // namespace fd::model

#endif  // FD_MODEL_RUNTIME_GROUP_NORM_KERNEL_H_

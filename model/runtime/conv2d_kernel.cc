// See conv2d_kernel.h for why the kernel is chosen here and not by at::conv2d.
#include "model/runtime/conv2d_kernel.h"

#include <ATen/Context.h>
#include <torch/torch.h>

namespace fd::model {
namespace {

// A float32 CPU tensor that oneDNN can take (built in and not turned off).
bool OneDnnFloatOnCpu(const torch::Tensor& t) {
  return t.is_cpu() && t.scalar_type() == torch::kFloat32 && at::hasMKLDNN() &&
         at::globalContext().userEnabledMkldnn();
}

bool NeedsAutograd(const torch::Tensor& x, const torch::Tensor& weight, const torch::Tensor& bias) {
  return torch::GradMode::is_enabled() &&
         (x.requires_grad() || weight.requires_grad() || (bias.defined() && bias.requires_grad()));
}

}  // namespace

torch::Tensor Conv2dForward(const torch::Tensor& x, const torch::Tensor& weight,
                            const torch::Tensor& bias, int64_t stride, int64_t padding) {
  // Only channels-last inputs (the networks that convert to it): on NCHW
  // latents, calling oneDNN directly for the batch-1 convolutions that ATen
  // gives the im2col kernel was not faster in whole frames (config B, batch
  // 1: 144-149 against 135-143 ms), although 2.5x faster for a [1, 32, 16, 16]
  // 3x3 convolution alone.
  const bool direct = OneDnnFloatOnCpu(x) && weight.scalar_type() == torch::kFloat32 &&
                      !NeedsAutograd(x, weight, bias) && x.dim() == 4 &&
                      x.is_contiguous(at::MemoryFormat::ChannelsLast) && !x.is_contiguous();
  if (!direct) return torch::conv2d(x, weight, bias, stride, padding);
  // oneDNN reorders the weight into its blocked layout on every call either
  // way; the output follows the input's memory format.
  return at::mkldnn_convolution(x, weight, bias, {padding, padding}, {stride, stride}, {1, 1},
                                /*groups=*/1);
}

bool UseChannelsLast(const torch::Tensor& x) {
  return x.defined() && x.dim() == 4 && OneDnnFloatOnCpu(x) && !torch::GradMode::is_enabled();
}

torch::Tensor ToChannelsLastForInference(const torch::Tensor& x) {
  return UseChannelsLast(x) ? x.contiguous(at::MemoryFormat::ChannelsLast) : x;
}

}  // namespace fd::model

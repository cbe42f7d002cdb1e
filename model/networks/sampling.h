// Downsample2D and Upsample2D, ported from diffusers v0.31.0
// src/diffusers/models/downsampling.py and upsampling.py, in the
// configuration the UNet/ControlNet/VAE blocks use (use_conv=True, no norm,
// no transposed conv; checkpoint key `conv`).
#ifndef FD_MODEL_NETWORKS_SAMPLING_H_
#define FD_MODEL_NETWORKS_SAMPLING_H_

#include <torch/nn/module.h>
#include <torch/nn/pimpl.h>
#include <torch/types.h>

#include <cstdint>
#include <vector>

#include "model/lora/lora_layers.h"

namespace fd::model {

// diffusers Downsample2D(channels, use_conv=True, out_channels, padding):
// a stride-2 3x3 conv. With padding 0 (the VAE encoder) the input is first
// padded by one zero row/column at the bottom/right, as diffusers does.
class Downsample2DImpl : public torch::nn::Module {
 public:
  Downsample2DImpl(int64_t channels, int64_t out_channels, int64_t padding);

  // x: [N, C, H, W] -> [N, out, ceil(H/2), ceil(W/2)] (padding 1 or 0)
  torch::Tensor forward(const torch::Tensor& x);

  LoraConv2d conv{nullptr};

 private:
  int64_t padding_;
};
TORCH_MODULE(Downsample2D);

// diffusers Upsample2D(channels, use_conv=True, out_channels): nearest
// upsampling (x2, or to `output_size` when given: the UNet passes the skip
// tensor's size when the latent is not a multiple of 2^num_upsamplers),
// then a 3x3 conv. bfloat16 inputs are upsampled in float32 like diffusers.
class Upsample2DImpl : public torch::nn::Module {
 public:
  Upsample2DImpl(int64_t channels, int64_t out_channels);

  // x: [N, C, H, W] -> [N, out, 2H, 2W] or [N, out, output_size...]
  torch::Tensor forward(const torch::Tensor& x, const std::vector<int64_t>& output_size = {});

  LoraConv2d conv{nullptr};
};
TORCH_MODULE(Upsample2D);

}  // namespace fd::model

#endif  // FD_MODEL_NETWORKS_SAMPLING_H_

// ResnetBlock2D, ported from diffusers v0.31.0 src/diffusers/models/resnet.py
// with the configuration every UNet/ControlNet/VAE block here uses:
// time_embedding_norm "default", non_linearity "swish" (SiLU), no up/down
// sampling inside the block, conv_shortcut (1x1) iff in != out channels,
// dropout 0 (inference).
#ifndef FD_MODEL_NETWORKS_RESNET_H_
#define FD_MODEL_NETWORKS_RESNET_H_

#include <torch/nn/module.h>
#include <torch/nn/modules/normalization.h>
#include <torch/nn/pimpl.h>
#include <torch/types.h>

#include <cstdint>

#include "model/lora/lora_layers.h"

namespace fd::model {

struct ResnetBlock2DOptions {
  int64_t in_channels = 0;
  int64_t out_channels = 0;
  int64_t temb_channels = 0;  // 0: no time embedding (VAE), no time_emb_proj
  int64_t groups = 32;
  double eps = 1e-6;
  double output_scale_factor = 1.0;
};

class ResnetBlock2DImpl : public torch::nn::Module {
 public:
  explicit ResnetBlock2DImpl(const ResnetBlock2DOptions& options);

  // x: [N, in, H, W], temb: [N, temb_channels] or undefined -> [N, out, H, W]
  torch::Tensor forward(const torch::Tensor& x, const torch::Tensor& temb = {});

  torch::nn::GroupNorm norm1{nullptr};
  LoraConv2d conv1{nullptr};
  LoraLinear time_emb_proj{nullptr};  // null without a time embedding
  torch::nn::GroupNorm norm2{nullptr};
  LoraConv2d conv2{nullptr};
  LoraConv2d conv_shortcut{nullptr};  // null when in == out

 private:
  double output_scale_factor_;
};
TORCH_MODULE(ResnetBlock2D);

}  // namespace fd::model

#endif  // FD_MODEL_NETWORKS_RESNET_H_

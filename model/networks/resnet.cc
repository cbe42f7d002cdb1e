// Port of diffusers v0.31.0 ResnetBlock2D (src/diffusers/models/resnet.py).
#include "model/networks/resnet.h"

#include <torch/torch.h>

#include "model/runtime/group_norm_kernel.h"

namespace fd::model {

ResnetBlock2DImpl::ResnetBlock2DImpl(const ResnetBlock2DOptions& o)
    : output_scale_factor_(o.output_scale_factor) {
  namespace nn = torch::nn;
  norm1 = register_module("norm1",
                          nn::GroupNorm(nn::GroupNormOptions(o.groups, o.in_channels).eps(o.eps)));
  conv1 = register_module("conv1", LoraConv2d(o.in_channels, o.out_channels, 3, 1, 1));
  if (o.temb_channels > 0) {
    time_emb_proj = register_module("time_emb_proj", LoraLinear(o.temb_channels, o.out_channels));
  }
  norm2 = register_module("norm2",
                          nn::GroupNorm(nn::GroupNormOptions(o.groups, o.out_channels).eps(o.eps)));
  conv2 = register_module("conv2", LoraConv2d(o.out_channels, o.out_channels, 3, 1, 1));
  if (o.in_channels != o.out_channels) {
    conv_shortcut =
        register_module("conv_shortcut", LoraConv2d(o.in_channels, o.out_channels, 1, 1, 0));
  }
}

torch::Tensor ResnetBlock2DImpl::forward(const torch::Tensor& x, const torch::Tensor& temb) {
  // x: [N, in, H, W]
  torch::Tensor h = conv1(torch::silu(GroupNormForward(*norm1, x)));  // [N, out, H, W]
  if (time_emb_proj && temb.defined()) {
    // temb: [N, temb_channels] -> [N, out, 1, 1]
    h = h + time_emb_proj(torch::silu(temb)).unsqueeze(-1).unsqueeze(-1);
  }
  h = conv2(torch::silu(GroupNormForward(*norm2, h)));  // [N, out, H, W]
  torch::Tensor shortcut = conv_shortcut ? conv_shortcut(x) : x;
  torch::Tensor out = shortcut + h;
  if (output_scale_factor_ != 1.0) out = out / output_scale_factor_;
  return out;  // [N, out, H, W]
}

}  // namespace fd::model

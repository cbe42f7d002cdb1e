// Port of diffusers v0.31.0 Transformer2DModel (continuous input path:
// _operate_on_continuous_inputs / _get_output_for_continuous_inputs).
#include "model/networks/transformer_2d.h"

#include <torch/torch.h>

namespace fd::model {

Transformer2DModelImpl::Transformer2DModelImpl(const Transformer2DOptions& o) {
  namespace nn = torch::nn;
  const int64_t inner_dim = o.num_attention_heads * o.attention_head_dim;
  norm = register_module(
      "norm", nn::GroupNorm(nn::GroupNormOptions(o.norm_num_groups, o.in_channels).eps(1e-6)));
  if (o.use_linear_projection) {
    proj_in_linear = register_module("proj_in", LoraLinear(o.in_channels, inner_dim));
  } else {
    proj_in_conv = register_module("proj_in", LoraConv2d(o.in_channels, inner_dim, 1));
  }
  transformer_blocks = register_module("transformer_blocks", nn::ModuleList());
  BasicTransformerBlockOptions block;
  block.dim = inner_dim;
  block.num_attention_heads = o.num_attention_heads;
  block.attention_head_dim = o.attention_head_dim;
  block.cross_attention_dim = o.cross_attention_dim;
  block.upcast_attention = o.upcast_attention;
  for (int64_t i = 0; i < o.num_layers; ++i) {
    blocks_.emplace_back(block);
    transformer_blocks->push_back(blocks_.back());
  }
  if (o.use_linear_projection) {
    proj_out_linear = register_module("proj_out", LoraLinear(inner_dim, o.in_channels));
  } else {
    proj_out_conv = register_module("proj_out", LoraConv2d(inner_dim, o.in_channels, 1));
  }
}

torch::Tensor Transformer2DModelImpl::forward(const torch::Tensor& x,
                                              const torch::Tensor& encoder_hidden_states) {
  // x: [B, C, H, W]
  const int64_t batch = x.size(0), height = x.size(2), width = x.size(3);
  torch::Tensor h = norm(x);
  if (proj_in_conv) h = proj_in_conv(h);  // [B, inner, H, W]
  const int64_t channels = h.size(1);
  h = h.permute({0, 2, 3, 1}).reshape({batch, height * width, channels});  // [B, HW, C]
  if (proj_in_linear) h = proj_in_linear(h);                               // [B, HW, inner]
  const bool checkpoint = ShouldCheckpoint();
  for (BasicTransformerBlock& block : blocks_) {
    if (!checkpoint) {
      h = block(h, encoder_hidden_states);  // [B, HW, inner]
      continue;
    }
    // The block is captured by value: backward calls it again later.
    h = Checkpoint(
        [block](const std::vector<torch::Tensor>& in) mutable { return block(in[0], in[1]); },
        {h, encoder_hidden_states});  // [B, HW, inner]
  }
  if (proj_out_linear) {
    h = proj_out_linear(h);  // [B, HW, C]
    h = h.reshape({batch, height, width, h.size(2)}).permute({0, 3, 1, 2}).contiguous();
  } else {
    h = h.reshape({batch, height, width, h.size(2)}).permute({0, 3, 1, 2}).contiguous();
    h = proj_out_conv(h);  // [B, C, H, W]
  }
  return h + x;
}

}  // namespace fd::model

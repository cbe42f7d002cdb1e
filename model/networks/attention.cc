// Port of diffusers v0.31.0 BasicTransformerBlock / FeedForward
// (src/diffusers/models/attention.py) and GEGLU (activations.py).
#include "model/networks/attention.h"

#include <torch/torch.h>

namespace fd::model {

GEGLUImpl::GEGLUImpl(int64_t dim_in, int64_t dim_out) {
  proj = register_module("proj", LoraLinear(dim_in, dim_out * 2));
}

torch::Tensor GEGLUImpl::forward(const torch::Tensor& x) {
  std::vector<torch::Tensor> parts = proj(x).chunk(2, -1);  // 2 x [..., dim_out]
  return parts[0] * torch::gelu(parts[1]);
}

FeedForwardImpl::FeedForwardImpl(int64_t dim, int64_t mult) {
  const int64_t inner_dim = dim * mult;
  geglu_ = GEGLU(dim, inner_dim);
  out_ = LoraLinear(inner_dim, dim);
  net = register_module("net", torch::nn::ModuleList(geglu_, torch::nn::Dropout(0.0), out_));
}

torch::Tensor FeedForwardImpl::forward(const torch::Tensor& x) {
  // x: [..., dim] -> [..., 4*dim] -> [..., dim]
  return out_(geglu_(x));
}

BasicTransformerBlockImpl::BasicTransformerBlockImpl(const BasicTransformerBlockOptions& o) {
  namespace nn = torch::nn;
  auto layer_norm = [&]() {
    return nn::LayerNorm(nn::LayerNormOptions({o.dim}).eps(o.norm_eps).elementwise_affine(true));
  };
  AttentionOptions self_attn;
  self_attn.query_dim = o.dim;
  self_attn.heads = o.num_attention_heads;
  self_attn.dim_head = o.attention_head_dim;
  self_attn.upcast_attention = o.upcast_attention;
  AttentionOptions cross_attn = self_attn;
  cross_attn.cross_attention_dim = o.cross_attention_dim;

  norm1 = register_module("norm1", layer_norm());
  attn1 = register_module("attn1", Attention(self_attn));
  norm2 = register_module("norm2", layer_norm());
  attn2 = register_module("attn2", Attention(cross_attn));
  norm3 = register_module("norm3", layer_norm());
  ff = register_module("ff", FeedForward(o.dim));
}

torch::Tensor BasicTransformerBlockImpl::forward(const torch::Tensor& hidden_states,
                                                 const torch::Tensor& encoder_hidden_states) {
  // hidden_states: [B, L, dim]
  torch::Tensor h = attn1(norm1(hidden_states)) + hidden_states;
  h = attn2(norm2(h), encoder_hidden_states) + h;
  h = ff(norm3(h)) + h;
  return h;  // [B, L, dim]
}

}  // namespace fd::model

// BasicTransformerBlock, FeedForward and GEGLU, ported from diffusers v0.31.0
// src/diffusers/models/attention.py (and activations.py for GEGLU) in the
// SD1.5 configuration: norm_type "layer_norm", self-attention (attn1),
// cross-attention (attn2), GEGLU feed-forward, no attention bias, dropout 0.
#ifndef FD_MODEL_NETWORKS_ATTENTION_H_
#define FD_MODEL_NETWORKS_ATTENTION_H_

#include <torch/nn/module.h>
#include <torch/nn/modules/container/modulelist.h>
#include <torch/nn/modules/normalization.h>
#include <torch/nn/pimpl.h>
#include <torch/types.h>

#include <cstdint>

#include "model/lora/lora_layers.h"
#include "model/networks/attention_processor.h"

namespace fd::model {

// diffusers GEGLU(dim_in, dim_out): proj = Linear(dim_in, 2*dim_out);
// hidden, gate = proj(x).chunk(2, -1); hidden * gelu(gate) (exact gelu).
class GEGLUImpl : public torch::nn::Module {
 public:
  GEGLUImpl(int64_t dim_in, int64_t dim_out);

  // x: [..., dim_in] -> [..., dim_out]
  torch::Tensor forward(const torch::Tensor& x);

  LoraLinear proj{nullptr};
};
TORCH_MODULE(GEGLU);

// diffusers FeedForward(dim, activation_fn="geglu", mult=4):
// net = [GEGLU(dim, 4*dim), Dropout, Linear(4*dim, dim)]  (keys net.0.proj,
// net.2).
class FeedForwardImpl : public torch::nn::Module {
 public:
  explicit FeedForwardImpl(int64_t dim, int64_t mult = 4);

  // x: [..., dim] -> [..., dim]
  torch::Tensor forward(const torch::Tensor& x);

  torch::nn::ModuleList net{nullptr};

 private:
  GEGLU geglu_{nullptr};
  LoraLinear out_{nullptr};
};
TORCH_MODULE(FeedForward);

struct BasicTransformerBlockOptions {
  int64_t dim = 0;
  int64_t num_attention_heads = 8;
  int64_t attention_head_dim = 64;
  int64_t cross_attention_dim = 0;  // 0: attn2 attends to the block's input
  bool upcast_attention = false;
  double norm_eps = 1e-5;
};

class BasicTransformerBlockImpl : public torch::nn::Module {
 public:
  explicit BasicTransformerBlockImpl(const BasicTransformerBlockOptions& options);

  // hidden_states: [B, L, dim], encoder_hidden_states: [B, Lk, cross_dim]
  // -> [B, L, dim]
  torch::Tensor forward(const torch::Tensor& hidden_states,
                        const torch::Tensor& encoder_hidden_states);

  torch::nn::LayerNorm norm1{nullptr};
  Attention attn1{nullptr};
  torch::nn::LayerNorm norm2{nullptr};
  Attention attn2{nullptr};
  torch::nn::LayerNorm norm3{nullptr};
  FeedForward ff{nullptr};
};
TORCH_MODULE(BasicTransformerBlock);

}  // namespace fd::model

#endif  // FD_MODEL_NETWORKS_ATTENTION_H_

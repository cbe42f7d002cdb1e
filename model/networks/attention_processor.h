// Attention, ported from diffusers v0.31.0
// src/diffusers/models/attention_processor.py (class Attention with
// AttnProcessor / AttnProcessor2_0): the cross/self attention of the UNet's
// transformer blocks and the single-head spatial attention of the VAE
// mid-block (group_norm, residual_connection, rescale_output_factor,
// upcast_softmax).
#ifndef FD_MODEL_NETWORKS_ATTENTION_PROCESSOR_H_
#define FD_MODEL_NETWORKS_ATTENTION_PROCESSOR_H_

#include <torch/nn/module.h>
#include <torch/nn/modules/container/modulelist.h>
#include <torch/nn/modules/normalization.h>
#include <torch/nn/pimpl.h>
#include <torch/types.h>

#include <cstdint>

#include "model/lora/lora_layers.h"

namespace fd::model {

// softmax(q k^T * scale) v per head. q: [B, H, Lq, D], k/v: [B, H, Lk, D]
// -> [B, H, Lq, D]. Uses torch's scaled_dot_product_attention when the
// LibTorch version has it (>= 2.0; scale 1/sqrt(D)); otherwise diffusers'
// classic AttnProcessor path (bmm, scale, softmax, bmm; not
// baddbmm(beta=0), which reads uninitialised memory on LibTorch 1.13 CPU).
// `upcast_softmax` computes the softmax in float32 on the classic path.
torch::Tensor DotProductAttention(const torch::Tensor& q, const torch::Tensor& k,
                                  const torch::Tensor& v, bool upcast_softmax);

struct AttentionOptions {
  int64_t query_dim = 0;
  int64_t cross_attention_dim = 0;  // 0: self-attention (= query_dim)
  int64_t heads = 8;
  int64_t dim_head = 64;
  bool bias = false;  // to_q/to_k/to_v bias
  bool out_bias = true;
  bool upcast_attention = false;  // q, k in float32
  bool upcast_softmax = false;
  int64_t norm_num_groups = 0;  // > 0: GroupNorm on the input (VAE)
  double eps = 1e-5;            // of that GroupNorm
  bool residual_connection = false;
  double rescale_output_factor = 1.0;
};

class AttentionImpl : public torch::nn::Module {
 public:
  explicit AttentionImpl(const AttentionOptions& options);

  // hidden_states: [B, L, query_dim] or [B, C, H, W] (spatial, VAE);
  // encoder_hidden_states: [B, Lk, cross_attention_dim] or undefined
  // (self-attention) -> same shape as hidden_states.
  torch::Tensor forward(const torch::Tensor& hidden_states,
                        const torch::Tensor& encoder_hidden_states = {});

  torch::nn::GroupNorm group_norm{nullptr};  // null unless norm_num_groups > 0
  LoraLinear to_q{nullptr};
  LoraLinear to_k{nullptr};
  LoraLinear to_v{nullptr};
  torch::nn::ModuleList to_out{nullptr};  // [0] Linear, [1] Dropout (no weights)

 private:
  AttentionOptions options_;
  LoraLinear to_out_0_{nullptr};
};
TORCH_MODULE(Attention);

}  // namespace fd::model

#endif  // FD_MODEL_NETWORKS_ATTENTION_PROCESSOR_H_

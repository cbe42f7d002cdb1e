// Timestep embeddings, ported from diffusers v0.31.0
// src/diffusers/models/embeddings.py: get_timestep_embedding, Timesteps,
// TimestepEmbedding (linear_1 -> SiLU -> linear_2, no cond_proj/post_act).
#ifndef FD_MODEL_NETWORKS_EMBEDDINGS_H_
#define FD_MODEL_NETWORKS_EMBEDDINGS_H_

#include <torch/nn/module.h>
#include <torch/nn/pimpl.h>
#include <torch/types.h>

#include <cstdint>

#include "model/lora/lora_layers.h"

namespace fd::model {

// diffusers get_timestep_embedding (scale 1, max_period 10000):
// exponent = -ln(10000) * arange(half) / (half - freq_shift);
// emb = t[:, None] * exp(exponent)[None]; cat([sin, cos]) or, with
// flip_sin_to_cos, cat([cos, sin]); zero-padded when `dim` is odd.
// timesteps: [N] (any numeric dtype) -> [N, dim] float32.
torch::Tensor TimestepEmbeddingSinusoid(const torch::Tensor& timesteps, int64_t dim,
                                        bool flip_sin_to_cos, double freq_shift);

// diffusers Timesteps: no parameters.
class TimestepsImpl : public torch::nn::Module {
 public:
  TimestepsImpl(int64_t num_channels, bool flip_sin_to_cos, double freq_shift)
      : num_channels_(num_channels), flip_sin_to_cos_(flip_sin_to_cos), freq_shift_(freq_shift) {}

  // timesteps: [N] -> [N, num_channels] float32
  torch::Tensor forward(const torch::Tensor& timesteps) {
    return TimestepEmbeddingSinusoid(timesteps, num_channels_, flip_sin_to_cos_, freq_shift_);
  }

 private:
  int64_t num_channels_;
  bool flip_sin_to_cos_;
  double freq_shift_;
};
TORCH_MODULE(Timesteps);

// diffusers TimestepEmbedding(in_channels, time_embed_dim, act_fn="silu").
class TimestepEmbeddingImpl : public torch::nn::Module {
 public:
  TimestepEmbeddingImpl(int64_t in_channels, int64_t time_embed_dim);

  // sample: [N, in_channels] -> [N, time_embed_dim]
  torch::Tensor forward(const torch::Tensor& sample);

  LoraLinear linear_1{nullptr};
  LoraLinear linear_2{nullptr};
};
TORCH_MODULE(TimestepEmbedding);

}  // namespace fd::model

#endif  // FD_MODEL_NETWORKS_EMBEDDINGS_H_

// Port of diffusers v0.31.0 src/diffusers/models/embeddings.py (timestep
// embedding); see embeddings.h.
#include "model/networks/embeddings.h"

#include <torch/torch.h>

#include <cmath>

namespace fd::model {

torch::Tensor TimestepEmbeddingSinusoid(const torch::Tensor& timesteps, int64_t dim,
                                        bool flip_sin_to_cos, double freq_shift) {
  const int64_t half_dim = dim / 2;
  const auto f32 = torch::TensorOptions().dtype(torch::kFloat32).device(timesteps.device());
  // Same float32 operation order as diffusers, so the result is bit-identical.
  torch::Tensor exponent = -std::log(10000.0) * torch::arange(0, half_dim, f32);  // [half]
  exponent = exponent / (static_cast<double>(half_dim) - freq_shift);
  torch::Tensor emb = torch::exp(exponent);
  emb = timesteps.unsqueeze(1).to(torch::kFloat32) * emb.unsqueeze(0);  // [N, half]
  emb = torch::cat({torch::sin(emb), torch::cos(emb)}, -1);             // [N, 2*half]
  if (flip_sin_to_cos) {
    emb = torch::cat({emb.slice(1, half_dim), emb.slice(1, 0, half_dim)}, -1);
  }
  if (dim % 2 == 1) emb = torch::constant_pad_nd(emb, {0, 1, 0, 0});
  return emb;  // [N, dim]
}

TimestepEmbeddingImpl::TimestepEmbeddingImpl(int64_t in_channels, int64_t time_embed_dim) {
  linear_1 = register_module("linear_1", LoraLinear(in_channels, time_embed_dim));
  linear_2 = register_module("linear_2", LoraLinear(time_embed_dim, time_embed_dim));
}

torch::Tensor TimestepEmbeddingImpl::forward(const torch::Tensor& sample) {
  // sample: [N, in] -> [N, time_embed_dim]
  return linear_2(torch::silu(linear_1(sample)));
}

}  // namespace fd::model

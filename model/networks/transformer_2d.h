// Transformer2DModel for continuous (image-like) inputs, ported from
// diffusers v0.31.0 src/diffusers/models/transformers/transformer_2d.py:
// GroupNorm(eps 1e-6) -> proj_in (Linear, or 1x1 conv when
// use_linear_projection is false) -> BasicTransformerBlocks -> proj_out ->
// + residual. With gradient checkpointing on, each BasicTransformerBlock is
// checkpointed while training, as diffusers does.
#ifndef FD_MODEL_NETWORKS_TRANSFORMER_2D_H_
#define FD_MODEL_NETWORKS_TRANSFORMER_2D_H_

#include <torch/nn/module.h>
#include <torch/nn/modules/container/modulelist.h>
#include <torch/nn/modules/normalization.h>
#include <torch/nn/pimpl.h>
#include <torch/types.h>

#include <cstdint>
#include <memory>
#include <vector>

#include "model/lora/lora_layers.h"
#include "model/networks/attention.h"
#include "model/networks/gradient_checkpoint.h"

namespace fd::model {

struct Transformer2DOptions {
  int64_t num_attention_heads = 8;
  int64_t attention_head_dim = 64;
  int64_t in_channels = 0;
  int64_t num_layers = 1;
  int64_t cross_attention_dim = 0;
  int64_t norm_num_groups = 32;
  bool use_linear_projection = false;
  bool upcast_attention = false;
};

class Transformer2DModelImpl : public torch::nn::Module, public GradientCheckpointable {
 public:
  explicit Transformer2DModelImpl(const Transformer2DOptions& options);

  // x: [B, C, H, W], encoder_hidden_states: [B, L, cross_dim] -> [B, C, H, W]
  torch::Tensor forward(const torch::Tensor& x, const torch::Tensor& encoder_hidden_states);

  torch::nn::GroupNorm norm{nullptr};
  // Exactly one of each pair is set, by use_linear_projection.
  LoraLinear proj_in_linear{nullptr};
  LoraConv2d proj_in_conv{nullptr};
  torch::nn::ModuleList transformer_blocks{nullptr};
  LoraLinear proj_out_linear{nullptr};
  LoraConv2d proj_out_conv{nullptr};

 private:
  std::vector<BasicTransformerBlock> blocks_;
};
TORCH_MODULE(Transformer2DModel);

}  // namespace fd::model

#endif  // FD_MODEL_NETWORKS_TRANSFORMER_2D_H_

// ControlNetModel, ported from diffusers v0.31.0
// src/diffusers/models/controlnet.py (ControlNetModel,
// ControlNetConditioningEmbedding), and the FrameDiffuser authors'
// ControlNetModelEx (model.py): the same network with the condition encoder
// replaced by a 9-conv nn.Sequential (keys controlnet_cond_embedding.{0,2,..,
// 16}) for the 10-channel G-buffer, no channel-order flip.
#ifndef FD_MODEL_NETWORKS_CONTROLNET_H_
#define FD_MODEL_NETWORKS_CONTROLNET_H_

#include <torch/nn/module.h>
#include <torch/nn/modules/container/modulelist.h>
#include <torch/nn/pimpl.h>
#include <torch/types.h>

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "model/lora/lora_layers.h"
#include "model/networks/debug_taps.h"
#include "model/networks/embeddings.h"
#include "model/networks/model_configs.h"
#include "model/networks/unet_blocks.h"

namespace fd::model {

// diffusers ControlNetConditioningEmbedding: conv_in -> SiLU -> per width
// step (3x3 conv, SiLU, stride-2 3x3 conv, SiLU) -> conv_out.
class ControlNetConditioningEmbeddingImpl : public torch::nn::Module {
 public:
  ControlNetConditioningEmbeddingImpl(int64_t conditioning_embedding_channels,
                                      int64_t conditioning_channels,
                                      const std::vector<int64_t>& block_out_channels);

  // cond: [N, C_cond, 8h, 8w] -> [N, C0, h, w] (3 stride-2 convs for 4 widths)
  torch::Tensor forward(const torch::Tensor& cond);

  LoraConv2d conv_in{nullptr};
  torch::nn::ModuleList blocks{nullptr};
  LoraConv2d conv_out{nullptr};

 private:
  std::vector<LoraConv2d> blocks_;
};
TORCH_MODULE(ControlNetConditioningEmbedding);

// FrameDiffuser's ControlNetModelEx encoder: nn.Sequential(conv, SiLU, conv,
// ..., conv) of 9 3x3 convs (padding 1): 10->c0, c0->c0, c0->c1 (s2), c1->c1,
// c1->c2 (s2), c2->c2, c2->c3 (s2), c3->c3, c3->C0. The convs sit at the even
// Sequential indices 0..16 (the SiLUs have no weights).
class ControlNetConditioningEmbeddingExImpl : public torch::nn::Module {
 public:
  ControlNetConditioningEmbeddingExImpl(int64_t conditioning_embedding_channels,
                                        int64_t conditioning_channels,
                                        const std::vector<int64_t>& block_out_channels);

  // cond: [N, C_cond, 8h, 8w] -> [N, C0, h, w]
  torch::Tensor forward(const torch::Tensor& cond);

 private:
  std::vector<LoraConv2d> convs_;
};
TORCH_MODULE(ControlNetConditioningEmbeddingEx);

// The module tree of ControlNetModel / ControlNetModelEx; named_parameters()
// equals the state-dict keys. Construct with MakeControlNet / LoadControlNet.
// Thread-safety: forward/Run may run concurrently while weights are not
// modified.
class ControlNetModelImpl : public torch::nn::Module {
 public:
  // `layout` from ComputeControlNetLayout(config). Throws on unsupported
  // block types (MakeControlNet validates and does not throw).
  ControlNetModelImpl(const ControlNetConfig& config, const UNetLayout& layout,
                      ControlNetEmbeddingKind embedding);

  // diffusers ControlNetModel.forward (guess_mode false), torch-style.
  // sample: [N, in_channels, h, w] (the noisy latent only);
  // timesteps: [N]; encoder_hidden_states: [N, L, cross_dim];
  // controlnet_cond: [N, C_cond, 8h, 8w];
  // -> the residuals, each times conditioning_scale: one per UNet skip tensor
  // ([N, C_k, h_k, w_k]) followed by the mid-block residual (the vector
  // UNet2DConditionModel::forward takes as `control`).
  std::vector<torch::Tensor> forward(const torch::Tensor& sample, const torch::Tensor& timesteps,
                                     const torch::Tensor& encoder_hidden_states,
                                     const torch::Tensor& controlnet_cond,
                                     double conditioning_scale = 1.0, DebugTaps* taps = nullptr);

  // The two parts of forward that do not change between the denoising steps
  // of a frame, so that a sampler loop can compute them once (FramePipeline):
  // forward(sample, t, ehs, cond, s) ==
  //     ForwardEmbedded(sample, EmbedTime(t), ehs, EmbedCondition(cond), s),
  // bitwise, op for op.
  // timesteps: [N] -> time embedding [N, 4*C0] in the model's dtype.
  torch::Tensor EmbedTime(const torch::Tensor& timesteps);
  // controlnet_cond: [N, C_cond, 8h, 8w] -> condition embedding [N, C0, h, w]
  // (after the bgr flip where the config asks for it).
  torch::Tensor EmbedCondition(const torch::Tensor& controlnet_cond);
  // forward from step 2 on: sample [N, in_channels, h, w], time_emb
  // [N, 4*C0], encoder_hidden_states [N, L, cross_dim], cond_emb
  // [N, C0, h, w] -> the residuals, as forward.
  std::vector<torch::Tensor> ForwardEmbedded(const torch::Tensor& sample,
                                             const torch::Tensor& time_emb,
                                             const torch::Tensor& encoder_hidden_states,
                                             const torch::Tensor& cond_emb,
                                             double conditioning_scale = 1.0,
                                             DebugTaps* taps = nullptr);

  // Checked entry point: validates shapes (INVALID_ARGUMENT naming the
  // tensor), moves floating inputs to the model's device/dtype, timestep [],
  // [1] or [N]; INTERNAL on torch errors.
  absl::StatusOr<std::vector<torch::Tensor>> Run(const torch::Tensor& sample,
                                                 const torch::Tensor& timestep,
                                                 const torch::Tensor& encoder_hidden_states,
                                                 const torch::Tensor& controlnet_cond,
                                                 double conditioning_scale = 1.0,
                                                 DebugTaps* taps = nullptr);

  // Checked forms of EmbedTime (timestep [], [1] or [batch]), EmbedCondition
  // and ForwardEmbedded (time_emb [N, 4*C0], cond_emb [N, C0, h, w]):
  // INVALID_ARGUMENT naming the tensor, INTERNAL on torch errors.
  absl::StatusOr<torch::Tensor> RunTimeEmbedding(const torch::Tensor& timestep, int64_t batch);
  absl::StatusOr<torch::Tensor> RunConditionEmbedding(const torch::Tensor& controlnet_cond);
  absl::StatusOr<std::vector<torch::Tensor>> RunEmbedded(const torch::Tensor& sample,
                                                         const torch::Tensor& time_emb,
                                                         const torch::Tensor& encoder_hidden_states,
                                                         const torch::Tensor& cond_emb,
                                                         double conditioning_scale = 1.0);

  const ControlNetConfig& config() const { return config_; }
  // The condition image is this many times the latent (2 per width step).
  int64_t condition_factor() const {
    return int64_t{1} << (config_.conditioning_embedding_out_channels.size() - 1);
  }
  ControlNetEmbeddingKind embedding_kind() const { return embedding_kind_; }

  LoraConv2d conv_in{nullptr};
  Timesteps time_proj{nullptr};
  TimestepEmbedding time_embedding{nullptr};
  ControlNetConditioningEmbedding cond_embedding{nullptr};       // kDiffusers
  ControlNetConditioningEmbeddingEx cond_embedding_ex{nullptr};  // kFrameDiffuserEx
  torch::nn::ModuleList down_blocks{nullptr};
  torch::nn::ModuleList controlnet_down_blocks{nullptr};
  UNetMidBlock2DCrossAttn mid_block{nullptr};
  LoraConv2d controlnet_mid_block{nullptr};

 private:
  ControlNetConfig config_;
  UNetLayout layout_;
  ControlNetEmbeddingKind embedding_kind_;
  // INVALID_ARGUMENT unless sample is [N, in_channels, h, w] and
  // encoder_hidden_states [N, L, cross_dim].
  absl::Status CheckSampleAndText(const torch::Tensor& sample,
                                  const torch::Tensor& encoder_hidden_states) const;
  std::vector<std::shared_ptr<UNetDownBlock>> down_blocks_;
  std::vector<LoraConv2d> controlnet_down_blocks_;
};
TORCH_MODULE(ControlNetModel);

// Builds a ControlNet with zero weights (CPU, float32).
// INVALID_ARGUMENT / UNIMPLEMENTED for unsupported configurations.
absl::StatusOr<ControlNetModel> MakeControlNet(const ControlNetConfig& config,
                                               ControlNetEmbeddingKind embedding);

// Loads `dir`/config.json + diffusion_pytorch_model.safetensors strictly; the
// embedding kind is detected from the keys (else `_class_name`). Moves the
// model to `device` / `dtype`, eval mode.
// Errors: NOT_FOUND, INVALID_ARGUMENT (config, missing / unexpected keys,
// shape mismatches, all listed), UNIMPLEMENTED, INTERNAL.
// `files`: where `dir` is read from (model/checkpoint/file_source.h).
absl::StatusOr<ControlNetModel> LoadControlNet(const std::string& dir, torch::Device device,
                                               torch::Dtype dtype,
                                               const FileSource& files = DiskFiles());

}  // namespace fd::model

#endif  // FD_MODEL_NETWORKS_CONTROLNET_H_

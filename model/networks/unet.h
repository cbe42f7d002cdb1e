// UNet2DConditionModel, ported from diffusers v0.31.0
// src/diffusers/models/unets/unet_2d_condition.py, as the FrameDiffuser
// authors extend it (model.py UNet2DConditionModelEx): conv_in takes the noisy
// latent and the previous-frame latent concatenated on channels (8 = 4 + 4)
// while config.json keeps the base in_channels 4.
//
// Supported: the SD1.5 family (positional time embedding, no class/addition
// embeddings, CrossAttnDownBlock2D / DownBlock2D / UpBlock2D /
// CrossAttnUpBlock2D, UNetMidBlock2DCrossAttn, GEGLU transformers with linear
// or 1x1-conv projections); model_configs.h rejects anything else.
#ifndef FD_MODEL_NETWORKS_UNET_H_
#define FD_MODEL_NETWORKS_UNET_H_

#include <torch/nn/module.h>
#include <torch/nn/modules/container/modulelist.h>
#include <torch/nn/modules/normalization.h>
#include <torch/nn/pimpl.h>
#include <torch/types.h>

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "model/lora/lora_layers.h"
#include "model/networks/debug_taps.h"
#include "model/networks/embeddings.h"
#include "model/networks/model_configs.h"
#include "model/networks/unet_blocks.h"

namespace fd::model {

// The module tree of UNet2DConditionModel; named_parameters() equals the
// diffusers state-dict keys. Construct with MakeUNet / LoadUNet.
//
// Thread-safety: forward/Run may run concurrently (no state is mutated) as
// long as nobody changes weights or LoRA adapters meanwhile.
class UNet2DConditionModelImpl : public torch::nn::Module {
 public:
  // `layout` must come from ComputeUNetLayout(config); config.InputChannels()
  // gives conv_in's input channels. Throws on unsupported block types (use
  // MakeUNet, which validates and does not throw).
  UNet2DConditionModelImpl(const UNet2DConditionConfig& config, const UNetLayout& layout);

  // The diffusers forward, torch-style (throws c10::Error on bad input).
  // sample: [N, C_in, h, w]; timesteps: [N] (any numeric dtype);
  // encoder_hidden_states: [N, L, cross_attention_dim];
  // control: empty, or ControlNet residuals = the down-block residuals (one
  // per skip tensor) followed by the mid-block residual (ControlNet output);
  // taps: optional intermediate activations (golden `debug.*` names).
  // -> noise prediction [N, out_channels, h, w]
  torch::Tensor forward(const torch::Tensor& sample, const torch::Tensor& timesteps,
                        const torch::Tensor& encoder_hidden_states,
                        const std::vector<torch::Tensor>& control = {}, DebugTaps* taps = nullptr);

  // forward in two parts, so that a sampler loop can compute the time
  // embedding once per timestep value (FramePipeline):
  // forward(sample, t, ehs, control) ==
  //     ForwardEmbedded(sample, EmbedTime(t), ehs, control), bitwise.
  // timesteps: [N] -> [N, 4*C0] in the model's dtype.
  torch::Tensor EmbedTime(const torch::Tensor& timesteps);
  // forward from step 2 on; time_emb: [N, 4*C0]; the rest as forward.
  torch::Tensor ForwardEmbedded(const torch::Tensor& sample, const torch::Tensor& time_emb,
                                const torch::Tensor& encoder_hidden_states,
                                const std::vector<torch::Tensor>& control = {},
                                DebugTaps* taps = nullptr);

  // ForwardEmbedded in two halves, so that the ControlNet can run beside the
  // down path on another thread (FramePipeline's companion thread): the
  // down path (conv_in, down blocks, mid block) does not read the ControlNet
  // residuals, only the up path adds them to the skip tensors and the mid
  // block's output. ForwardUp(ForwardDown(x, emb, ehs), emb, ehs, control) ==
  // ForwardEmbedded(x, emb, ehs, control), bitwise (the same operations).
  struct DownPath {
    torch::Tensor hidden_states;             // the mid block's output [N, C_last, h', w']
    std::vector<torch::Tensor> res_samples;  // skip tensors, as ResidualShapes lists them
    int64_t sample_height = 0;               // of the sample, for the upsample sizes
    int64_t sample_width = 0;
  };
  DownPath ForwardDown(const torch::Tensor& sample, const torch::Tensor& time_emb,
                       const torch::Tensor& encoder_hidden_states, DebugTaps* taps = nullptr);
  // -> noise prediction [N, out_channels, h, w]; `down` is consumed.
  torch::Tensor ForwardUp(DownPath down, const torch::Tensor& time_emb,
                          const torch::Tensor& encoder_hidden_states,
                          const std::vector<torch::Tensor>& control = {},
                          DebugTaps* taps = nullptr);

  // Checked entry point: validates shapes (INVALID_ARGUMENT naming the
  // tensor), moves floating inputs to the model's device and dtype, accepts a
  // timestep of shape [], [1] or [N] (broadcast to the batch, like diffusers),
  // and converts torch errors to INTERNAL.
  absl::StatusOr<torch::Tensor> Run(const torch::Tensor& sample, const torch::Tensor& timestep,
                                    const torch::Tensor& encoder_hidden_states,
                                    const std::vector<torch::Tensor>& control = {},
                                    DebugTaps* taps = nullptr);

  // Checked forms of EmbedTime (timestep [], [1] or [batch]) and
  // ForwardEmbedded (time_emb [N, 4*C0]), as Run.
  absl::StatusOr<torch::Tensor> RunTimeEmbedding(const torch::Tensor& timestep, int64_t batch);
  absl::StatusOr<torch::Tensor> RunEmbedded(const torch::Tensor& sample,
                                            const torch::Tensor& time_emb,
                                            const torch::Tensor& encoder_hidden_states,
                                            const std::vector<torch::Tensor>& control = {});
  // Checked forms of ForwardDown and ForwardUp, as RunEmbedded (RunUp
  // checks `control` against the sample `down` came from).
  absl::StatusOr<DownPath> RunDown(const torch::Tensor& sample, const torch::Tensor& time_emb,
                                   const torch::Tensor& encoder_hidden_states);
  absl::StatusOr<torch::Tensor> RunUp(DownPath down, const torch::Tensor& time_emb,
                                      const torch::Tensor& encoder_hidden_states,
                                      const std::vector<torch::Tensor>& control = {});

  const UNet2DConditionConfig& config() const { return config_; }
  const UNetLayout& layout() const { return layout_; }
  int64_t input_channels() const { return config_.InputChannels(); }
  // Number of down-block skip tensors = ControlNet down residuals expected.
  int64_t num_down_residuals() const;
  // The shapes of the ControlNet residuals `control` must have for a sample
  // of [batch, C_in, height, width]: one per skip tensor, then the mid one.
  std::vector<std::vector<int64_t>> ResidualShapes(int64_t batch, int64_t height,
                                                   int64_t width) const;
  // 2^(number of upsamplers): latent sizes that are not multiples of it use
  // the explicit upsample_size path.
  int64_t overall_up_factor() const { return overall_up_factor_; }

  LoraConv2d conv_in{nullptr};
  Timesteps time_proj{nullptr};
  TimestepEmbedding time_embedding{nullptr};
  torch::nn::ModuleList down_blocks{nullptr};
  UNetMidBlock2DCrossAttn mid_block{nullptr};
  torch::nn::ModuleList up_blocks{nullptr};
  torch::nn::GroupNorm conv_norm_out{nullptr};
  LoraConv2d conv_out{nullptr};

 private:
  UNet2DConditionConfig config_;
  UNetLayout layout_;
  std::vector<std::shared_ptr<UNetDownBlock>> down_blocks_;
  std::vector<std::shared_ptr<UNetUpBlock>> up_blocks_;
  int64_t overall_up_factor_ = 1;
  // INVALID_ARGUMENT unless sample, encoder_hidden_states and control have
  // the shapes Run documents.
  absl::Status CheckInputs(const torch::Tensor& sample, const torch::Tensor& encoder_hidden_states,
                           const std::vector<torch::Tensor>& control) const;
  absl::Status CheckControl(int64_t batch, int64_t height, int64_t width,
                            const std::vector<torch::Tensor>& control) const;
  absl::Status CheckTimeEmbedding(const torch::Tensor& time_emb, int64_t batch) const;
};
TORCH_MODULE(UNet2DConditionModel);

// Builds a UNet with zero weights on the CPU in float32.
// INVALID_ARGUMENT / UNIMPLEMENTED for configurations this port does not
// support; INTERNAL on torch errors.
absl::StatusOr<UNet2DConditionModel> MakeUNet(const UNet2DConditionConfig& config);

// Loads `dir`/config.json and `dir`/diffusion_pytorch_model.safetensors (the
// diffusers save_pretrained layout), strictly: every parameter must be in
// the file with its shape and no key may be left over. conv_in's input
// channels come from the weight (UNet2DConditionModelEx: [C0, 8, 3, 3] while
// the config says 4); a 4-channel conv_in is zero-padded to 8 input channels,
// as the authors' add_extra_conditions(["gbuffer"]) does, when
// `frame_diffuser_input` is true. The model is moved to `device` / `dtype`
// (float32, float16, bfloat16) and put in eval mode.
// Errors: NOT_FOUND (missing file), INVALID_ARGUMENT (bad config, missing /
// unexpected keys or shape mismatches, all listed), UNIMPLEMENTED, INTERNAL.
// `files`: where `dir` is read from (model/checkpoint/file_source.h).
absl::StatusOr<UNet2DConditionModel> LoadUNet(const std::string& dir, torch::Device device,
                                              torch::Dtype dtype, bool frame_diffuser_input = true,
                                              const FileSource& files = DiskFiles());

}  // namespace fd::model

#endif  // FD_MODEL_NETWORKS_UNET_H_

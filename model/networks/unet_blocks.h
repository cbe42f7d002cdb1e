// UNet, ControlNet and VAE blocks, ported from diffusers v0.31.0
// src/diffusers/models/unets/unet_2d_blocks.py: CrossAttnDownBlock2D,
// DownBlock2D, UNetMidBlock2DCrossAttn, UpBlock2D, CrossAttnUpBlock2D (UNet,
// ControlNet) and DownEncoderBlock2D, UNetMidBlock2D, UpDecoderBlock2D (VAE),
// without FreeU, dual cross-attention or T2I-adapter residuals (not used by
// the SD1.5 family). The UNet/ControlNet blocks checkpoint their resnets when
// gradient checkpointing is on, as diffusers' do (the VAE blocks do not: the
// trainer trains the VAE on small crops).
#ifndef FD_MODEL_NETWORKS_UNET_BLOCKS_H_
#define FD_MODEL_NETWORKS_UNET_BLOCKS_H_

#include <torch/nn/module.h>
#include <torch/nn/modules/container/modulelist.h>
#include <torch/nn/pimpl.h>
#include <torch/types.h>

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "model/networks/attention_processor.h"
#include "model/networks/gradient_checkpoint.h"
#include "model/networks/model_configs.h"
#include "model/networks/resnet.h"
#include "model/networks/sampling.h"
#include "model/networks/transformer_2d.h"

namespace fd::model {

// The arguments diffusers' get_down_block / get_up_block pass on, with the
// SD1.5 defaults.
struct UNetBlockOptions {
  int64_t num_layers = 1;
  int64_t in_channels = 0;
  int64_t out_channels = 0;
  int64_t prev_output_channel = 0;  // up blocks only
  int64_t temb_channels = 0;        // 0: none (VAE)
  bool add_downsample = false;      // down blocks
  bool add_upsample = false;        // up blocks
  double resnet_eps = 1e-5;
  int64_t resnet_groups = 32;
  double output_scale_factor = 1.0;
  int64_t downsample_padding = 1;
  // Cross-attention blocks only.
  int64_t num_attention_heads = 8;
  int64_t cross_attention_dim = 768;
  int64_t transformer_layers_per_block = 1;
  bool use_linear_projection = false;
  bool upcast_attention = false;
};

// The options of one UNet/ControlNet block from its layout (model_configs.h)
// and the config's shared settings (norm, projection, attention upcast).
UNetBlockOptions BlockOptionsFromLayout(const UNetCommonConfig& config,
                                        const UNetBlockLayout& block, int64_t temb_channels);

// What a down block returns: diffusers' (hidden_states, output_states).
struct DownBlockOutput {
  torch::Tensor hidden_states;             // [N, out, H', W']
  std::vector<torch::Tensor> res_samples;  // the skip tensors, in order
};

// Common interface of the UNet/ControlNet down blocks.
class UNetDownBlock : public torch::nn::Module, public GradientCheckpointable {
 public:
  // x: [N, in, H, W], temb: [N, temb], encoder_hidden_states: [N, L, cross]
  virtual DownBlockOutput Forward(const torch::Tensor& x, const torch::Tensor& temb,
                                  const torch::Tensor& encoder_hidden_states) = 0;
};

// Common interface of the UNet up blocks.
class UNetUpBlock : public torch::nn::Module, public GradientCheckpointable {
 public:
  // x: [N, prev, H, W]; res_samples: the skip tensors of this block, consumed
  // from the back; upsample_size: empty (x2) or the [H, W] to upsample to.
  virtual torch::Tensor Forward(const torch::Tensor& x, std::vector<torch::Tensor> res_samples,
                                const torch::Tensor& temb,
                                const torch::Tensor& encoder_hidden_states,
                                const std::vector<int64_t>& upsample_size) = 0;
  virtual int64_t num_resnets() const = 0;
};

// diffusers CrossAttnDownBlock2D (with_attention) and DownBlock2D (without):
// num_layers x (resnet [+ transformer]), then an optional stride-2
// downsampler; every resnet/attention output and the downsampler output are
// skip tensors.
class DownBlock2DImpl : public UNetDownBlock {
 public:
  DownBlock2DImpl(const UNetBlockOptions& options, bool with_attention);

  DownBlockOutput Forward(const torch::Tensor& x, const torch::Tensor& temb,
                          const torch::Tensor& encoder_hidden_states) override;

  torch::nn::ModuleList attentions{nullptr};  // null for DownBlock2D
  torch::nn::ModuleList resnets{nullptr};
  torch::nn::ModuleList downsamplers{nullptr};

 private:
  std::vector<ResnetBlock2D> resnets_;
  std::vector<Transformer2DModel> attentions_;
  Downsample2D downsampler_{nullptr};
};

// diffusers UpBlock2D (without attention) and CrossAttnUpBlock2D (with):
// num_layers x (concat skip -> resnet [-> transformer]), then an optional
// upsampler.
class UpBlock2DImpl : public UNetUpBlock {
 public:
  UpBlock2DImpl(const UNetBlockOptions& options, bool with_attention);

  torch::Tensor Forward(const torch::Tensor& x, std::vector<torch::Tensor> res_samples,
                        const torch::Tensor& temb, const torch::Tensor& encoder_hidden_states,
                        const std::vector<int64_t>& upsample_size) override;
  int64_t num_resnets() const override { return static_cast<int64_t>(resnets_.size()); }

  torch::nn::ModuleList attentions{nullptr};  // null for UpBlock2D
  torch::nn::ModuleList resnets{nullptr};
  torch::nn::ModuleList upsamplers{nullptr};

 private:
  std::vector<ResnetBlock2D> resnets_;
  std::vector<Transformer2DModel> attentions_;
  Upsample2D upsampler_{nullptr};
};

// Builds the down/up block named by a diffusers block type
// ("CrossAttnDownBlock2D", "DownBlock2D" / "UpBlock2D",
// "CrossAttnUpBlock2D"). INVALID_ARGUMENT for any other type.
absl::StatusOr<std::shared_ptr<UNetDownBlock>> MakeDownBlock(const std::string& type,
                                                             const UNetBlockOptions& options);
absl::StatusOr<std::shared_ptr<UNetUpBlock>> MakeUpBlock(const std::string& type,
                                                         const UNetBlockOptions& options);

// diffusers UNetMidBlock2DCrossAttn: resnet, then num_layers x
// (transformer, resnet). Uses in_channels, temb_channels, resnet_*,
// output_scale_factor and the attention options.
class UNetMidBlock2DCrossAttnImpl : public torch::nn::Module, public GradientCheckpointable {
 public:
  explicit UNetMidBlock2DCrossAttnImpl(const UNetBlockOptions& options);

  // x: [N, C, H, W] -> [N, C, H, W]
  torch::Tensor forward(const torch::Tensor& x, const torch::Tensor& temb,
                        const torch::Tensor& encoder_hidden_states);

  torch::nn::ModuleList attentions{nullptr};
  torch::nn::ModuleList resnets{nullptr};

 private:
  std::vector<ResnetBlock2D> resnets_;
  std::vector<Transformer2DModel> attentions_;
};
TORCH_MODULE(UNetMidBlock2DCrossAttn);

// diffusers UNetMidBlock2D as the VAE uses it: resnet, then num_layers x
// ([single-head spatial Attention with GroupNorm and residual,] resnet); no
// time embedding. `attention_head_dim` = channels per head (VAE: in_channels).
class UNetMidBlock2DImpl : public torch::nn::Module {
 public:
  UNetMidBlock2DImpl(const UNetBlockOptions& options, bool add_attention,
                     int64_t attention_head_dim);

  // x: [N, C, H, W] -> [N, C, H, W]
  torch::Tensor forward(const torch::Tensor& x);

  torch::nn::ModuleList attentions{nullptr};  // null without attention
  torch::nn::ModuleList resnets{nullptr};

 private:
  std::vector<ResnetBlock2D> resnets_;
  std::vector<Attention> attentions_;
};
TORCH_MODULE(UNetMidBlock2D);

// diffusers DownEncoderBlock2D: num_layers resnets (no time embedding), then
// an optional Downsample2D (the VAE uses padding 0).
class DownEncoderBlock2DImpl : public torch::nn::Module {
 public:
  explicit DownEncoderBlock2DImpl(const UNetBlockOptions& options);

  // x: [N, in, H, W] -> [N, out, H', W']
  torch::Tensor forward(const torch::Tensor& x);

  torch::nn::ModuleList resnets{nullptr};
  torch::nn::ModuleList downsamplers{nullptr};

 private:
  std::vector<ResnetBlock2D> resnets_;
  Downsample2D downsampler_{nullptr};
};
TORCH_MODULE(DownEncoderBlock2D);

// diffusers UpDecoderBlock2D: num_layers resnets, then an optional Upsample2D.
class UpDecoderBlock2DImpl : public torch::nn::Module {
 public:
  explicit UpDecoderBlock2DImpl(const UNetBlockOptions& options);

  // x: [N, in, H, W] -> [N, out, 2H, 2W] (or H, W without upsampler)
  torch::Tensor forward(const torch::Tensor& x);

  torch::nn::ModuleList resnets{nullptr};
  torch::nn::ModuleList upsamplers{nullptr};

 private:
  std::vector<ResnetBlock2D> resnets_;
  Upsample2D upsampler_{nullptr};
};
TORCH_MODULE(UpDecoderBlock2D);

}  // namespace fd::model

#endif  // FD_MODEL_NETWORKS_UNET_BLOCKS_H_

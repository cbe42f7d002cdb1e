// AutoencoderKL, ported from diffusers v0.31.0
// src/diffusers/models/autoencoders/autoencoder_kl.py (AutoencoderKL),
// autoencoders/vae.py (Encoder, Decoder, DiagonalGaussianDistribution).
//
// The VAE never applies the scaling factor: as the FrameDiffuser pipeline
// does, the caller computes prev_latent = (mean + std * noise) *
// scaling_factor and decodes latents / scaling_factor.
#ifndef FD_MODEL_NETWORKS_VAE_H_
#define FD_MODEL_NETWORKS_VAE_H_

#include <torch/nn/module.h>
#include <torch/nn/modules/container/modulelist.h>
#include <torch/nn/modules/normalization.h>
#include <torch/nn/pimpl.h>
#include <torch/types.h>

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "model/lora/lora_layers.h"
#include "model/networks/debug_taps.h"
#include "model/networks/model_configs.h"
#include "model/networks/unet_blocks.h"

namespace fd::model {

// diffusers vae.Encoder (double_z): conv_in -> DownEncoderBlock2D x n
// (stride-2 downsample with bottom/right zero padding except the last) ->
// UNetMidBlock2D (attention) -> GroupNorm -> SiLU -> conv_out (2*latent).
class VaeEncoderImpl : public torch::nn::Module {
 public:
  explicit VaeEncoderImpl(const AutoencoderKLConfig& config);

  // x: [N, 3, H, W] -> [N, 2*latent, H/2^(n-1), W/2^(n-1)]
  // taps: "encoder.down_blocks.{k}", "encoder.mid_block", "encoder.conv_out".
  torch::Tensor forward(const torch::Tensor& x, DebugTaps* taps = nullptr);

  LoraConv2d conv_in{nullptr};
  torch::nn::ModuleList down_blocks{nullptr};
  UNetMidBlock2D mid_block{nullptr};
  torch::nn::GroupNorm conv_norm_out{nullptr};
  LoraConv2d conv_out{nullptr};

 private:
  std::vector<DownEncoderBlock2D> down_blocks_;
};
TORCH_MODULE(VaeEncoder);

// diffusers vae.Decoder: conv_in -> UNetMidBlock2D -> UpDecoderBlock2D x n
// (nearest x2 + conv except the last) -> GroupNorm -> SiLU -> conv_out.
class VaeDecoderImpl : public torch::nn::Module {
 public:
  explicit VaeDecoderImpl(const AutoencoderKLConfig& config);

  // z: [N, latent, h, w] -> [N, 3, h*2^(n-1), w*2^(n-1)]
  // taps: "decoder.conv_in", "decoder.mid_block", "decoder.up_blocks.{k}".
  torch::Tensor forward(const torch::Tensor& z, DebugTaps* taps = nullptr);

  LoraConv2d conv_in{nullptr};
  UNetMidBlock2D mid_block{nullptr};
  torch::nn::ModuleList up_blocks{nullptr};
  torch::nn::GroupNorm conv_norm_out{nullptr};
  LoraConv2d conv_out{nullptr};

 private:
  std::vector<UpDecoderBlock2D> up_blocks_;
};
TORCH_MODULE(VaeDecoder);

// diffusers DiagonalGaussianDistribution of an encoded image.
struct LatentPosterior {
  torch::Tensor moments;  // quant_conv output [N, 2*latent, h, w] (mean ++ logvar)
  torch::Tensor mean;     // [N, latent, h, w]
  torch::Tensor logvar;   // clamped to [-30, 20]
  torch::Tensor std;      // exp(0.5 * logvar)

  // mean + std * noise (latent_dist.sample() with the given N(0,1) noise);
  // NOT scaled by the scaling factor.
  torch::Tensor Sample(const torch::Tensor& noise) const { return mean + std * noise; }
};

// The module tree of AutoencoderKL; named_parameters() equals the state-dict
// keys. Thread-safety: Encode/Decode may run concurrently while weights are
// not modified.
class AutoencoderKLImpl : public torch::nn::Module {
 public:
  explicit AutoencoderKLImpl(const AutoencoderKLConfig& config);

  // Torch-style (throws). image: [N, in_channels, H, W] in [-1, 1];
  // taps add "quant_conv". Encode and decode run channels-last inside on the
  // CPU at inference (model/runtime/conv2d_kernel.h); their outputs are
  // NCHW-contiguous either way.
  LatentPosterior encode(const torch::Tensor& image, DebugTaps* taps = nullptr);
  // z: [N, latent, h, w] (unscaled) -> [N, out_channels, H, W] in ~[-1, 1];
  // taps add "post_quant_conv".
  torch::Tensor decode(const torch::Tensor& z, DebugTaps* taps = nullptr);

  // Checked entry points: validate shapes (INVALID_ARGUMENT; H and W must be
  // multiples of the downsampling factor), move inputs to the model's
  // device/dtype, INTERNAL on torch errors.
  absl::StatusOr<LatentPosterior> Encode(const torch::Tensor& image, DebugTaps* taps = nullptr);
  absl::StatusOr<torch::Tensor> Decode(const torch::Tensor& z, DebugTaps* taps = nullptr);

  const AutoencoderKLConfig& config() const { return config_; }
  // 2^(number of down blocks - 1): image size / latent size.
  int64_t downsampling_factor() const;

  VaeEncoder encoder{nullptr};
  VaeDecoder decoder{nullptr};
  LoraConv2d quant_conv{nullptr};       // null unless use_quant_conv
  LoraConv2d post_quant_conv{nullptr};  // null unless use_post_quant_conv

 private:
  AutoencoderKLConfig config_;
};
TORCH_MODULE(AutoencoderKL);

// Builds an AutoencoderKL with zero weights (CPU, float32).
// INVALID_ARGUMENT / UNIMPLEMENTED for unsupported configurations.
absl::StatusOr<AutoencoderKL> MakeVae(const AutoencoderKLConfig& config);

// Loads `dir`/config.json + diffusion_pytorch_model.safetensors strictly and
// moves the model to `device` / `dtype` (eval mode).
// Errors: NOT_FOUND, INVALID_ARGUMENT (config, missing / unexpected keys,
// shape mismatches, all listed), UNIMPLEMENTED, INTERNAL.
// `files`: where `dir` is read from (model/checkpoint/file_source.h).
absl::StatusOr<AutoencoderKL> LoadVae(const std::string& dir, torch::Device device,
                                      torch::Dtype dtype, const FileSource& files = DiskFiles());

}  // namespace fd::model

#endif  // FD_MODEL_NETWORKS_VAE_H_

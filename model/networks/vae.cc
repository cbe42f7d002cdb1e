// Port of diffusers v0.31.0 AutoencoderKL / Encoder / Decoder /
// DiagonalGaussianDistribution; see vae.h.
#include "model/networks/vae.h"

#include <torch/torch.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "base/status_macros.h"
#include "model/checkpoint/checkpoint_loading.h"
#include "model/checkpoint/safetensors.h"
#include "model/checkpoint/state_dict_loader.h"
#include "model/runtime/conv2d_kernel.h"
#include "model/runtime/group_norm_kernel.h"
#include "model/runtime/torch_call.h"

namespace fd::model {
namespace {

std::string ShapeOf(const torch::Tensor& t) {
  if (!t.defined()) return "undefined";
  return absl::StrCat("[", absl::StrJoin(t.sizes().vec(), ", "), "]");
}

// Encoder/Decoder resnets and norms use eps 1e-6 (hard-coded in vae.py).
constexpr double kVaeEps = 1e-6;

UNetBlockOptions VaeBlockOptions(const AutoencoderKLConfig& config, int64_t num_layers,
                                 int64_t in_channels, int64_t out_channels) {
  UNetBlockOptions o;
  o.num_layers = num_layers;
  o.in_channels = in_channels;
  o.out_channels = out_channels;
  o.temb_channels = 0;
  o.resnet_eps = kVaeEps;
  o.resnet_groups = config.norm_num_groups;
  o.downsample_padding = 0;
  return o;
}

torch::nn::GroupNorm MakeGroupNorm(int64_t groups, int64_t channels) {
  return torch::nn::GroupNorm(torch::nn::GroupNormOptions(groups, channels).eps(kVaeEps));
}

}  // namespace

// ---------------------------------------------------------------------------
// Encoder

VaeEncoderImpl::VaeEncoderImpl(const AutoencoderKLConfig& config) {
  const std::vector<int64_t>& channels = config.block_out_channels;
  conv_in = register_module("conv_in", LoraConv2d(config.in_channels, channels.at(0), 3, 1, 1));
  down_blocks = register_module("down_blocks", torch::nn::ModuleList());
  int64_t output_channel = channels[0];
  for (size_t i = 0; i < channels.size(); ++i) {
    const int64_t input_channel = output_channel;
    output_channel = channels[i];
    UNetBlockOptions o =
        VaeBlockOptions(config, config.layers_per_block, input_channel, output_channel);
    o.add_downsample = i + 1 != channels.size();
    down_blocks_.emplace_back(o);
    down_blocks->push_back(down_blocks_.back());
  }
  UNetBlockOptions mid = VaeBlockOptions(config, 1, channels.back(), channels.back());
  mid_block = register_module("mid_block",
                              UNetMidBlock2D(mid, config.mid_block_add_attention, channels.back()));
  conv_norm_out =
      register_module("conv_norm_out", MakeGroupNorm(config.norm_num_groups, channels.back()));
  conv_out =
      register_module("conv_out", LoraConv2d(channels.back(), 2 * config.latent_channels, 3, 1, 1));
}

torch::Tensor VaeEncoderImpl::forward(const torch::Tensor& x, DebugTaps* taps) {
  // x: [N, 3, H, W]
  torch::Tensor h = conv_in(x);  // [N, C0, H, W]
  for (size_t k = 0; k < down_blocks_.size(); ++k) {
    h = down_blocks_[k](h);  // [N, C_k, H/2^k', W/2^k']
    Tap(
        taps, [k] { return absl::StrCat("encoder.down_blocks.", k); }, h);
  }
  h = mid_block(h);
  Tap(taps, "encoder.mid_block", h);
  h = conv_out(torch::silu(GroupNormForward(*conv_norm_out, h)));  // [N, 2*latent, h, w]
  Tap(taps, "encoder.conv_out", h);
  return h;
}

// ---------------------------------------------------------------------------
// Decoder

VaeDecoderImpl::VaeDecoderImpl(const AutoencoderKLConfig& config) {
  const std::vector<int64_t>& channels = config.block_out_channels;
  conv_in =
      register_module("conv_in", LoraConv2d(config.latent_channels, channels.back(), 3, 1, 1));
  UNetBlockOptions mid = VaeBlockOptions(config, 1, channels.back(), channels.back());
  mid_block = register_module("mid_block",
                              UNetMidBlock2D(mid, config.mid_block_add_attention, channels.back()));
  up_blocks = register_module("up_blocks", torch::nn::ModuleList());
  const std::vector<int64_t> reversed(channels.rbegin(), channels.rend());
  int64_t output_channel = reversed[0];
  for (size_t i = 0; i < reversed.size(); ++i) {
    const int64_t prev_output_channel = output_channel;
    output_channel = reversed[i];
    UNetBlockOptions o =
        VaeBlockOptions(config, config.layers_per_block + 1, prev_output_channel, output_channel);
    o.add_upsample = i + 1 != reversed.size();
    up_blocks_.emplace_back(o);
    up_blocks->push_back(up_blocks_.back());
  }
  conv_norm_out =
      register_module("conv_norm_out", MakeGroupNorm(config.norm_num_groups, channels[0]));
  conv_out = register_module("conv_out", LoraConv2d(channels[0], config.out_channels, 3, 1, 1));
}

torch::Tensor VaeDecoderImpl::forward(const torch::Tensor& z, DebugTaps* taps) {
  // z: [N, latent, h, w]
  torch::Tensor h = conv_in(z);  // [N, C_last, h, w]
  Tap(taps, "decoder.conv_in", h);
  h = mid_block(h);
  Tap(taps, "decoder.mid_block", h);
  for (size_t k = 0; k < up_blocks_.size(); ++k) {
    h = up_blocks_[k](h);  // [N, C_k, 2^k' h, 2^k' w]
    Tap(
        taps, [k] { return absl::StrCat("decoder.up_blocks.", k); }, h);
  }
  return conv_out(torch::silu(GroupNormForward(*conv_norm_out, h)));  // [N, 3, H, W]
}

// ---------------------------------------------------------------------------
// AutoencoderKL

AutoencoderKLImpl::AutoencoderKLImpl(const AutoencoderKLConfig& config) : config_(config) {
  const int64_t latent = config.latent_channels;
  encoder = register_module("encoder", VaeEncoder(config));
  decoder = register_module("decoder", VaeDecoder(config));
  if (config.use_quant_conv) {
    quant_conv = register_module("quant_conv", LoraConv2d(2 * latent, 2 * latent, 1));
  }
  if (config.use_post_quant_conv) {
    post_quant_conv = register_module("post_quant_conv", LoraConv2d(latent, latent, 1));
  }
}

int64_t AutoencoderKLImpl::downsampling_factor() const {
  return int64_t{1} << (config_.block_out_channels.size() - 1);
}

LatentPosterior AutoencoderKLImpl::encode(const torch::Tensor& image, DebugTaps* taps) {
  // image: [N, 3, H, W]
  // Channels-last on the CPU at inference (model/runtime/conv2d_kernel.h).
  torch::Tensor h =
      encoder(ToChannelsLastForInference(image), taps).contiguous();  // [N, 2*latent, h, w]
  LatentPosterior posterior;
  posterior.moments = quant_conv ? quant_conv(h) : h;
  Tap(taps, "quant_conv", posterior.moments);
  std::vector<torch::Tensor> parts = posterior.moments.chunk(2, 1);
  posterior.mean = parts[0];                               // [N, latent, h, w]
  posterior.logvar = torch::clamp(parts[1], -30.0, 20.0);  // [N, latent, h, w]
  posterior.std = torch::exp(0.5 * posterior.logvar);
  return posterior;
}

torch::Tensor AutoencoderKLImpl::decode(const torch::Tensor& z, DebugTaps* taps) {
  // z: [N, latent, h, w]
  torch::Tensor h = post_quant_conv ? post_quant_conv(z) : z;
  Tap(taps, "post_quant_conv", h);
  return decoder(ToChannelsLastForInference(h), taps).contiguous();  // [N, 3, H, W]
}

absl::StatusOr<LatentPosterior> AutoencoderKLImpl::Encode(const torch::Tensor& image,
                                                          DebugTaps* taps) {
  const int64_t f = downsampling_factor();
  if (!image.defined() || image.dim() != 4 || image.size(1) != config_.in_channels ||
      image.size(2) % f != 0 || image.size(3) % f != 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("VAE encode: image must be [N, ", config_.in_channels,
                     ", H, W] with H and W multiples of ", f, ", got ", ShapeOf(image)));
  }
  return TorchCall("VAE encode", [&]() -> absl::StatusOr<LatentPosterior> {
    torch::NoGradGuard no_grad;
    return encode(image.to(encoder->conv_in->weight.options()), taps);
  });
}

absl::StatusOr<torch::Tensor> AutoencoderKLImpl::Decode(const torch::Tensor& z, DebugTaps* taps) {
  if (!z.defined() || z.dim() != 4 || z.size(1) != config_.latent_channels) {
    return absl::InvalidArgumentError(absl::StrCat(
        "VAE decode: latents must be [N, ", config_.latent_channels, ", h, w], got ", ShapeOf(z)));
  }
  return TorchCall("VAE decode", [&]() -> absl::StatusOr<torch::Tensor> {
    torch::NoGradGuard no_grad;
    return decode(z.to(decoder->conv_in->weight.options()), taps);
  });
}

absl::StatusOr<AutoencoderKL> MakeVae(const AutoencoderKLConfig& config) {
  for (const std::string& type : config.down_block_types) {
    if (type != "DownEncoderBlock2D") {
      return absl::UnimplementedError(
          absl::StrCat("AutoencoderKL: unsupported down block type '", type, "'"));
    }
  }
  for (const std::string& type : config.up_block_types) {
    if (type != "UpDecoderBlock2D") {
      return absl::UnimplementedError(
          absl::StrCat("AutoencoderKL: unsupported up block type '", type, "'"));
    }
  }
  if (config.block_out_channels.empty() ||
      config.block_out_channels.size() != config.down_block_types.size() ||
      config.block_out_channels.size() != config.up_block_types.size()) {
    return absl::InvalidArgumentError(
        "AutoencoderKL: block_out_channels, down_block_types and up_block_types must have the "
        "same, non-zero length");
  }
  return TorchCall("MakeVae",
                   [&]() -> absl::StatusOr<AutoencoderKL> { return AutoencoderKL(config); });
}

absl::StatusOr<AutoencoderKL> LoadVae(const std::string& dir, torch::Device device,
                                      torch::Dtype dtype, const FileSource& files) {
  FD_ASSIGN_OR_RETURN(AutoencoderKLConfig config,
                      LoadAutoencoderKLConfig(dir + "/config.json", files));
  FD_ASSIGN_OR_RETURN(std::unique_ptr<SafetensorsFile> file,
                      files.OpenSafetensors(dir + "/diffusion_pytorch_model.safetensors"));
  FD_ASSIGN_OR_RETURN(AutoencoderKL vae, MakeVae(config));
  FD_RETURN_IF_ERROR(LoadStateDict(*vae, *file));
  FD_RETURN_IF_ERROR(MoveModule(*vae, device, dtype));
  return vae;
}

}  // namespace fd::model

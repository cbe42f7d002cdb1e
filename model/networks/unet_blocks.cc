// Port of diffusers v0.31.0 src/diffusers/models/unets/unet_2d_blocks.py;
// see unet_blocks.h.
#include "model/networks/unet_blocks.h"

#include <torch/torch.h>

#include <utility>

#include "absl/strings/str_cat.h"

namespace fd::model {
namespace {

ResnetBlock2DOptions ResnetOptions(const UNetBlockOptions& o, int64_t in_channels,
                                   int64_t out_channels) {
  ResnetBlock2DOptions r;
  r.in_channels = in_channels;
  r.out_channels = out_channels;
  r.temb_channels = o.temb_channels;
  r.groups = o.resnet_groups;
  r.eps = o.resnet_eps;
  r.output_scale_factor = o.output_scale_factor;
  return r;
}

// Transformer2DModel(num_attention_heads, channels // num_attention_heads,
// in_channels=channels, ...), as the cross-attention blocks build it.
Transformer2DOptions TransformerOptions(const UNetBlockOptions& o, int64_t channels) {
  Transformer2DOptions t;
  t.num_attention_heads = o.num_attention_heads;
  t.attention_head_dim = channels / o.num_attention_heads;
  t.in_channels = channels;
  t.num_layers = o.transformer_layers_per_block;
  t.cross_attention_dim = o.cross_attention_dim;
  t.norm_num_groups = o.resnet_groups;
  t.use_linear_projection = o.use_linear_projection;
  t.upcast_attention = o.upcast_attention;
  return t;
}

// resnet(h, temb), or diffusers' torch.utils.checkpoint.checkpoint(
// create_custom_forward(resnet), hidden_states, temb) when `checkpoint`.
torch::Tensor RunResnet(ResnetBlock2D& resnet, const torch::Tensor& h, const torch::Tensor& temb,
                        bool checkpoint) {
  if (!checkpoint) return resnet(h, temb);
  // The module is captured by value: backward calls the function again
  // after this forward has returned.
  return Checkpoint(
      [resnet](const std::vector<torch::Tensor>& in) mutable { return resnet(in[0], in[1]); },
      {h, temb});
}

}  // namespace

UNetBlockOptions BlockOptionsFromLayout(const UNetCommonConfig& config,
                                        const UNetBlockLayout& block, int64_t temb_channels) {
  UNetBlockOptions o;
  o.num_layers = block.num_layers;
  o.in_channels = block.in_channels;
  o.out_channels = block.out_channels;
  o.prev_output_channel = block.prev_output_channel;
  o.temb_channels = temb_channels;
  o.add_downsample = block.add_sampler;
  o.add_upsample = block.add_sampler;
  o.resnet_eps = config.norm_eps;
  o.resnet_groups = config.norm_num_groups;
  o.downsample_padding = config.downsample_padding;
  o.num_attention_heads = block.num_attention_heads > 0 ? block.num_attention_heads : 1;
  o.cross_attention_dim = block.cross_attention_dim;
  o.transformer_layers_per_block = block.transformer_layers;
  o.use_linear_projection = config.use_linear_projection;
  o.upcast_attention = config.upcast_attention;
  return o;
}

// ---------------------------------------------------------------------------
// CrossAttnDownBlock2D / DownBlock2D

DownBlock2DImpl::DownBlock2DImpl(const UNetBlockOptions& o, bool with_attention) {
  if (with_attention) attentions = register_module("attentions", torch::nn::ModuleList());
  resnets = register_module("resnets", torch::nn::ModuleList());
  for (int64_t i = 0; i < o.num_layers; ++i) {
    const int64_t in_channels = i == 0 ? o.in_channels : o.out_channels;
    resnets_.emplace_back(ResnetOptions(o, in_channels, o.out_channels));
    resnets->push_back(resnets_.back());
    if (with_attention) {
      attentions_.emplace_back(TransformerOptions(o, o.out_channels));
      attentions->push_back(attentions_.back());
    }
  }
  if (o.add_downsample) {
    downsampler_ = Downsample2D(o.out_channels, o.out_channels, o.downsample_padding);
    downsamplers = register_module("downsamplers", torch::nn::ModuleList(downsampler_));
  }
}

DownBlockOutput DownBlock2DImpl::Forward(const torch::Tensor& x, const torch::Tensor& temb,
                                         const torch::Tensor& encoder_hidden_states) {
  // x: [N, in, H, W]
  DownBlockOutput out;
  torch::Tensor h = x;
  const bool checkpoint = ShouldCheckpoint();
  for (size_t i = 0; i < resnets_.size(); ++i) {
    h = RunResnet(resnets_[i], h, temb, checkpoint);                         // [N, out, H, W]
    if (!attentions_.empty()) h = attentions_[i](h, encoder_hidden_states);  // [N, out, H, W]
    out.res_samples.push_back(h);
  }
  if (downsampler_) {
    h = downsampler_(h);  // [N, out, ceil(H/2), ceil(W/2)]
    out.res_samples.push_back(h);
  }
  out.hidden_states = h;
  return out;
}

// ---------------------------------------------------------------------------
// UpBlock2D / CrossAttnUpBlock2D

UpBlock2DImpl::UpBlock2DImpl(const UNetBlockOptions& o, bool with_attention) {
  if (with_attention) attentions = register_module("attentions", torch::nn::ModuleList());
  resnets = register_module("resnets", torch::nn::ModuleList());
  for (int64_t i = 0; i < o.num_layers; ++i) {
    const int64_t res_skip_channels = i == o.num_layers - 1 ? o.in_channels : o.out_channels;
    const int64_t resnet_in_channels = i == 0 ? o.prev_output_channel : o.out_channels;
    resnets_.emplace_back(ResnetOptions(o, resnet_in_channels + res_skip_channels, o.out_channels));
    resnets->push_back(resnets_.back());
    if (with_attention) {
      attentions_.emplace_back(TransformerOptions(o, o.out_channels));
      attentions->push_back(attentions_.back());
    }
  }
  if (o.add_upsample) {
    upsampler_ = Upsample2D(o.out_channels, o.out_channels);
    upsamplers = register_module("upsamplers", torch::nn::ModuleList(upsampler_));
  }
}

torch::Tensor UpBlock2DImpl::Forward(const torch::Tensor& x, std::vector<torch::Tensor> res_samples,
                                     const torch::Tensor& temb,
                                     const torch::Tensor& encoder_hidden_states,
                                     const std::vector<int64_t>& upsample_size) {
  // x: [N, prev, H, W]
  torch::Tensor h = x;
  const bool checkpoint = ShouldCheckpoint();
  for (size_t i = 0; i < resnets_.size(); ++i) {
    torch::Tensor skip = std::move(res_samples.back());  // [N, skip, H, W]
    res_samples.pop_back();
    h = torch::cat({h, skip}, 1);                                            // [N, prev+skip, H, W]
    h = RunResnet(resnets_[i], h, temb, checkpoint);                         // [N, out, H, W]
    if (!attentions_.empty()) h = attentions_[i](h, encoder_hidden_states);  // [N, out, H, W]
  }
  if (upsampler_) h = upsampler_(h, upsample_size);  // [N, out, 2H, 2W] or upsample_size
  return h;
}

// ---------------------------------------------------------------------------

absl::StatusOr<std::shared_ptr<UNetDownBlock>> MakeDownBlock(const std::string& type,
                                                             const UNetBlockOptions& options) {
  if (type == "CrossAttnDownBlock2D") return std::make_shared<DownBlock2DImpl>(options, true);
  if (type == "DownBlock2D") return std::make_shared<DownBlock2DImpl>(options, false);
  return absl::InvalidArgumentError(absl::StrCat(
      "unsupported down block type '", type, "' (supported: CrossAttnDownBlock2D, DownBlock2D)"));
}

absl::StatusOr<std::shared_ptr<UNetUpBlock>> MakeUpBlock(const std::string& type,
                                                         const UNetBlockOptions& options) {
  if (type == "CrossAttnUpBlock2D") return std::make_shared<UpBlock2DImpl>(options, true);
  if (type == "UpBlock2D") return std::make_shared<UpBlock2DImpl>(options, false);
  return absl::InvalidArgumentError(absl::StrCat("unsupported up block type '", type,
                                                 "' (supported: UpBlock2D, CrossAttnUpBlock2D)"));
}

// ---------------------------------------------------------------------------
// UNetMidBlock2DCrossAttn

UNetMidBlock2DCrossAttnImpl::UNetMidBlock2DCrossAttnImpl(const UNetBlockOptions& o) {
  attentions = register_module("attentions", torch::nn::ModuleList());
  resnets = register_module("resnets", torch::nn::ModuleList());
  resnets_.emplace_back(ResnetOptions(o, o.in_channels, o.in_channels));
  resnets->push_back(resnets_.back());
  for (int64_t i = 0; i < o.num_layers; ++i) {
    attentions_.emplace_back(TransformerOptions(o, o.in_channels));
    attentions->push_back(attentions_.back());
    resnets_.emplace_back(ResnetOptions(o, o.in_channels, o.in_channels));
    resnets->push_back(resnets_.back());
  }
}

torch::Tensor UNetMidBlock2DCrossAttnImpl::forward(const torch::Tensor& x,
                                                   const torch::Tensor& temb,
                                                   const torch::Tensor& encoder_hidden_states) {
  // x: [N, C, H, W]
  // As diffusers: the first resnet runs plainly, the others checkpointed.
  torch::Tensor h = resnets_[0](x, temb);
  const bool checkpoint = ShouldCheckpoint();
  for (size_t i = 0; i < attentions_.size(); ++i) {
    h = attentions_[i](h, encoder_hidden_states);
    h = RunResnet(resnets_[i + 1], h, temb, checkpoint);
  }
  return h;  // [N, C, H, W]
}

// ---------------------------------------------------------------------------
// UNetMidBlock2D (VAE)

UNetMidBlock2DImpl::UNetMidBlock2DImpl(const UNetBlockOptions& o, bool add_attention,
                                       int64_t attention_head_dim) {
  if (add_attention) attentions = register_module("attentions", torch::nn::ModuleList());
  resnets = register_module("resnets", torch::nn::ModuleList());
  resnets_.emplace_back(ResnetOptions(o, o.in_channels, o.in_channels));
  resnets->push_back(resnets_.back());
  AttentionOptions a;
  a.query_dim = o.in_channels;
  a.heads = o.in_channels / attention_head_dim;
  a.dim_head = attention_head_dim;
  a.bias = true;
  a.upcast_softmax = true;
  a.norm_num_groups = o.resnet_groups;  // resnet_time_scale_shift "default"
  a.eps = o.resnet_eps;
  a.residual_connection = true;
  a.rescale_output_factor = o.output_scale_factor;
  for (int64_t i = 0; i < o.num_layers; ++i) {
    if (add_attention) {
      attentions_.emplace_back(a);
      attentions->push_back(attentions_.back());
    }
    resnets_.emplace_back(ResnetOptions(o, o.in_channels, o.in_channels));
    resnets->push_back(resnets_.back());
  }
}

torch::Tensor UNetMidBlock2DImpl::forward(const torch::Tensor& x) {
  // x: [N, C, H, W]
  torch::Tensor h = resnets_[0](x);
  for (size_t i = 1; i < resnets_.size(); ++i) {
    if (!attentions_.empty()) h = attentions_[i - 1](h);
    h = resnets_[i](h);
  }
  return h;  // [N, C, H, W]
}

// ---------------------------------------------------------------------------
// DownEncoderBlock2D / UpDecoderBlock2D (VAE)

DownEncoderBlock2DImpl::DownEncoderBlock2DImpl(const UNetBlockOptions& o) {
  resnets = register_module("resnets", torch::nn::ModuleList());
  for (int64_t i = 0; i < o.num_layers; ++i) {
    resnets_.emplace_back(
        ResnetOptions(o, i == 0 ? o.in_channels : o.out_channels, o.out_channels));
    resnets->push_back(resnets_.back());
  }
  if (o.add_downsample) {
    downsampler_ = Downsample2D(o.out_channels, o.out_channels, o.downsample_padding);
    downsamplers = register_module("downsamplers", torch::nn::ModuleList(downsampler_));
  }
}

torch::Tensor DownEncoderBlock2DImpl::forward(const torch::Tensor& x) {
  // x: [N, in, H, W]
  torch::Tensor h = x;
  for (ResnetBlock2D& resnet : resnets_) h = resnet(h);  // [N, out, H, W]
  if (downsampler_) h = downsampler_(h);                 // [N, out, H/2, W/2]
  return h;
}

UpDecoderBlock2DImpl::UpDecoderBlock2DImpl(const UNetBlockOptions& o) {
  resnets = register_module("resnets", torch::nn::ModuleList());
  for (int64_t i = 0; i < o.num_layers; ++i) {
    resnets_.emplace_back(
        ResnetOptions(o, i == 0 ? o.in_channels : o.out_channels, o.out_channels));
    resnets->push_back(resnets_.back());
  }
  if (o.add_upsample) {
    upsampler_ = Upsample2D(o.out_channels, o.out_channels);
    upsamplers = register_module("upsamplers", torch::nn::ModuleList(upsampler_));
  }
}

torch::Tensor UpDecoderBlock2DImpl::forward(const torch::Tensor& x) {
  // x: [N, in, H, W]
  torch::Tensor h = x;
  for (ResnetBlock2D& resnet : resnets_) h = resnet(h);  // [N, out, H, W]
  if (upsampler_) h = upsampler_(h);                     // [N, out, 2H, 2W]
  return h;
}

}  // namespace fd::model

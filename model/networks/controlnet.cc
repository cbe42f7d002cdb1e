// Port of diffusers v0.31.0 ControlNetModel (src/diffusers/models/
// controlnet.py) and FrameDiffuser's ControlNetModelEx; see controlnet.h.
#include "model/networks/controlnet.h"

#include <torch/torch.h>

#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "base/status_macros.h"
#include "model/checkpoint/checkpoint_loading.h"
#include "model/checkpoint/safetensors.h"
#include "model/checkpoint/state_dict_loader.h"
#include "model/runtime/conv2d_kernel.h"
#include "model/runtime/torch_call.h"

namespace fd::model {
namespace {

std::string ShapeOf(const torch::Tensor& t) {
  if (!t.defined()) return "undefined";
  return absl::StrCat("[", absl::StrJoin(t.sizes().vec(), ", "), "]");
}

}  // namespace

// ---------------------------------------------------------------------------
// ControlNetConditioningEmbedding (diffusers)

ControlNetConditioningEmbeddingImpl::ControlNetConditioningEmbeddingImpl(
    int64_t conditioning_embedding_channels, int64_t conditioning_channels,
    const std::vector<int64_t>& block_out_channels) {
  conv_in = register_module("conv_in",
                            LoraConv2d(conditioning_channels, block_out_channels.at(0), 3, 1, 1));
  blocks = register_module("blocks", torch::nn::ModuleList());
  for (size_t i = 0; i + 1 < block_out_channels.size(); ++i) {
    const int64_t channel_in = block_out_channels[i];
    const int64_t channel_out = block_out_channels[i + 1];
    blocks_.emplace_back(channel_in, channel_in, 3, 1, 1);
    blocks_.emplace_back(channel_in, channel_out, 3, 2, 1);
  }
  for (LoraConv2d& block : blocks_) blocks->push_back(block);
  conv_out = register_module(
      "conv_out", LoraConv2d(block_out_channels.back(), conditioning_embedding_channels, 3, 1, 1));
}

torch::Tensor ControlNetConditioningEmbeddingImpl::forward(const torch::Tensor& cond) {
  // cond: [N, C_cond, H, W]; channels-last on the CPU at inference
  // (model/runtime/conv2d_kernel.h: full-resolution, few channels).
  torch::Tensor h = torch::silu(conv_in(ToChannelsLastForInference(cond)));
  for (LoraConv2d& block : blocks_) h = torch::silu(block(h));
  return conv_out(h).contiguous();  // [N, C0, H/8, W/8]
}

// ---------------------------------------------------------------------------
// ControlNetModelEx's Sequential encoder

ControlNetConditioningEmbeddingExImpl::ControlNetConditioningEmbeddingExImpl(
    int64_t conditioning_embedding_channels, int64_t conditioning_channels,
    const std::vector<int64_t>& c) {
  struct Spec {
    int64_t in, out, stride;
  };
  const Spec specs[] = {{conditioning_channels, c.at(0), 1},
                        {c[0], c[0], 1},
                        {c[0], c.at(1), 2},
                        {c[1], c[1], 1},
                        {c[1], c.at(2), 2},
                        {c[2], c[2], 1},
                        {c[2], c.at(3), 2},
                        {c[3], c[3], 1},
                        {c[3], conditioning_embedding_channels, 1}};
  int index = 0;
  for (const Spec& s : specs) {
    convs_.push_back(
        register_module(std::to_string(index), LoraConv2d(s.in, s.out, 3, s.stride, 1)));
    index += 2;  // the SiLU in between has no weights
  }
}

torch::Tensor ControlNetConditioningEmbeddingExImpl::forward(const torch::Tensor& cond) {
  // cond: [N, C_cond, H, W]; channels-last on the CPU at inference
  // (model/runtime/conv2d_kernel.h: full-resolution, few channels).
  torch::Tensor h = ToChannelsLastForInference(cond);
  for (size_t i = 0; i < convs_.size(); ++i) {
    h = convs_[i](h);
    if (i + 1 < convs_.size()) h = torch::silu(h);
  }
  return h.contiguous();  // [N, C0, H/8, W/8]
}

// ---------------------------------------------------------------------------
// ControlNetModel

ControlNetModelImpl::ControlNetModelImpl(const ControlNetConfig& config, const UNetLayout& layout,
                                         ControlNetEmbeddingKind embedding)
    : config_(config), layout_(layout), embedding_kind_(embedding) {
  namespace nn = torch::nn;
  const int64_t c0 = config.block_out_channels.at(0);
  const int64_t temb = layout.time_embed_dim;
  conv_in = register_module("conv_in", LoraConv2d(config.in_channels, c0, 3, 1, 1));
  time_proj = register_module(
      "time_proj", Timesteps(c0, config.flip_sin_to_cos, static_cast<double>(config.freq_shift)));
  time_embedding = register_module("time_embedding", TimestepEmbedding(c0, temb));
  if (embedding == ControlNetEmbeddingKind::kFrameDiffuserEx) {
    cond_embedding_ex = register_module(
        "controlnet_cond_embedding",
        ControlNetConditioningEmbeddingEx(c0, config.ConditionChannels(),
                                          config.conditioning_embedding_out_channels));
  } else {
    cond_embedding = register_module(
        "controlnet_cond_embedding",
        ControlNetConditioningEmbedding(c0, config.ConditionChannels(),
                                        config.conditioning_embedding_out_channels));
  }

  down_blocks = register_module("down_blocks", nn::ModuleList());
  controlnet_down_blocks = register_module("controlnet_down_blocks", nn::ModuleList());
  // One 1x1 "zero conv" per skip tensor: conv_in's output, then each resnet
  // (+ attention) output and each downsampler output.
  controlnet_down_blocks_.emplace_back(c0, c0, 1);
  for (const UNetBlockLayout& block : layout.down_blocks) {
    down_blocks_.push_back(
        MakeDownBlock(block.type, BlockOptionsFromLayout(config, block, temb)).value());
    down_blocks->push_back(down_blocks_.back());
    const int64_t n = block.num_layers + (block.add_sampler ? 1 : 0);
    for (int64_t i = 0; i < n; ++i) {
      controlnet_down_blocks_.emplace_back(block.out_channels, block.out_channels, 1);
    }
  }
  for (LoraConv2d& conv : controlnet_down_blocks_) controlnet_down_blocks->push_back(conv);

  UNetBlockOptions mid = BlockOptionsFromLayout(config, layout.mid_block, temb);
  mid.output_scale_factor = config.mid_block_scale_factor;
  mid_block = register_module("mid_block", UNetMidBlock2DCrossAttn(mid));
  const int64_t mid_channels = layout.mid_block.out_channels;
  controlnet_mid_block =
      register_module("controlnet_mid_block", LoraConv2d(mid_channels, mid_channels, 1));
}

std::vector<torch::Tensor> ControlNetModelImpl::forward(const torch::Tensor& sample,
                                                        const torch::Tensor& timesteps,
                                                        const torch::Tensor& encoder_hidden_states,
                                                        const torch::Tensor& controlnet_cond,
                                                        double conditioning_scale,
                                                        DebugTaps* taps) {
  // 1. time, [N, 4*C0]
  torch::Tensor emb = EmbedTime(timesteps.to(sample.device()));
  if (taps != nullptr) {
    (*taps)["time_proj"] = time_proj(timesteps).to(sample.scalar_type());
    (*taps)["time_embedding"] = emb;
  }
  // 2. (condition half) [N, C0, h, w]
  torch::Tensor cond_emb = EmbedCondition(controlnet_cond);
  Tap(taps, "controlnet_cond_embedding", cond_emb);
  return ForwardEmbedded(sample, emb, encoder_hidden_states, cond_emb, conditioning_scale, taps);
}

torch::Tensor ControlNetModelImpl::EmbedTime(const torch::Tensor& timesteps) {
  // [N] -> [N, C0] -> [N, 4*C0]
  const torch::Tensor t_emb = time_proj(timesteps).to(conv_in->weight.scalar_type());
  return time_embedding(t_emb);
}

torch::Tensor ControlNetModelImpl::EmbedCondition(const torch::Tensor& controlnet_cond) {
  // 0. condition channel order (diffusers encoder only; ControlNetModelEx
  // feeds its G-buffer unchanged).
  torch::Tensor cond = controlnet_cond;
  if (cond_embedding && config_.controlnet_conditioning_channel_order == "bgr") {
    cond = torch::flip(cond, {1});
  }
  // [N, C_cond, 8h, 8w] -> [N, C0, h, w]
  return cond_embedding ? cond_embedding(cond) : cond_embedding_ex(cond);
}

std::vector<torch::Tensor> ControlNetModelImpl::ForwardEmbedded(
    const torch::Tensor& sample, const torch::Tensor& time_emb,
    const torch::Tensor& encoder_hidden_states, const torch::Tensor& cond_emb,
    double conditioning_scale, DebugTaps* taps) {
  const torch::Tensor& emb = time_emb;  // [N, 4*C0]

  // 2. pre-process: conv_in(sample) + condition embedding, [N, C0, h, w]
  torch::Tensor h = conv_in(sample);
  Tap(taps, "conv_in", h);
  h = h + cond_emb;

  // 3. down
  std::vector<torch::Tensor> res_samples = {h};
  for (size_t k = 0; k < down_blocks_.size(); ++k) {
    DownBlockOutput out = down_blocks_[k]->Forward(h, emb, encoder_hidden_states);
    h = out.hidden_states;
    if (taps != nullptr) {
      (*taps)[absl::StrCat("down_blocks.", k, ".hidden_states")] = h;
      for (size_t j = 0; j < out.res_samples.size(); ++j) {
        (*taps)[absl::StrCat("down_blocks.", k, ".res_samples.", j)] = out.res_samples[j];
      }
    }
    for (torch::Tensor& r : out.res_samples) res_samples.push_back(std::move(r));
  }

  // 4. mid
  h = mid_block(h, emb, encoder_hidden_states);  // [N, C_last, h', w']
  Tap(taps, "mid_block", h);

  // 5. control net blocks (zero convs), 6. scaling
  std::vector<torch::Tensor> residuals;
  residuals.reserve(res_samples.size() + 1);
  for (size_t i = 0; i < res_samples.size(); ++i) {
    residuals.push_back(controlnet_down_blocks_[i](res_samples[i]));
  }
  residuals.push_back(controlnet_mid_block(h));
  for (torch::Tensor& r : residuals) {
    r = r * conditioning_scale;
    if (config_.global_pool_conditions) r = torch::mean(r, {2, 3}, /*keepdim=*/true);
  }
  return residuals;
}

absl::Status ControlNetModelImpl::CheckSampleAndText(
    const torch::Tensor& sample, const torch::Tensor& encoder_hidden_states) const {
  if (!sample.defined() || sample.dim() != 4 || sample.size(1) != config_.in_channels) {
    return absl::InvalidArgumentError(absl::StrCat(
        "ControlNet: sample must be [N, ", config_.in_channels, ", h, w], got ", ShapeOf(sample)));
  }
  const int64_t batch = sample.size(0);
  const int64_t cross_dim = layout_.mid_block.cross_attention_dim;
  if (!encoder_hidden_states.defined() || encoder_hidden_states.dim() != 3 ||
      encoder_hidden_states.size(0) != batch || encoder_hidden_states.size(2) != cross_dim) {
    return absl::InvalidArgumentError(absl::StrCat("ControlNet: encoder_hidden_states must be [",
                                                   batch, ", L, ", cross_dim, "], got ",
                                                   ShapeOf(encoder_hidden_states)));
  }
  return absl::OkStatus();
}

namespace {

absl::Status CheckTimestep(const torch::Tensor& timestep, int64_t batch) {
  if (!timestep.defined() || timestep.dim() > 1 ||
      (timestep.dim() == 1 && timestep.size(0) != 1 && timestep.size(0) != batch)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "ControlNet: timestep must be a scalar, [1] or [", batch, "], got ", ShapeOf(timestep)));
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<std::vector<torch::Tensor>> ControlNetModelImpl::Run(
    const torch::Tensor& sample, const torch::Tensor& timestep,
    const torch::Tensor& encoder_hidden_states, const torch::Tensor& controlnet_cond,
    double conditioning_scale, DebugTaps* taps) {
  FD_RETURN_IF_ERROR(CheckSampleAndText(sample, encoder_hidden_states));
  const int64_t batch = sample.size(0);
  // The condition encoder downsamples by 2 per width step (3 for SD: 8x).
  const int64_t factor = condition_factor();
  if (!controlnet_cond.defined() || controlnet_cond.dim() != 4 ||
      controlnet_cond.size(0) != batch || controlnet_cond.size(1) != config_.ConditionChannels() ||
      controlnet_cond.size(2) != sample.size(2) * factor ||
      controlnet_cond.size(3) != sample.size(3) * factor) {
    return absl::InvalidArgumentError(
        absl::StrCat("ControlNet: controlnet_cond must be [", batch, ", ",
                     config_.ConditionChannels(), ", ", sample.size(2) * factor, ", ",
                     sample.size(3) * factor, "], got ", ShapeOf(controlnet_cond)));
  }
  FD_RETURN_IF_ERROR(CheckTimestep(timestep, batch));
  return TorchCall("ControlNet forward", [&]() -> absl::StatusOr<std::vector<torch::Tensor>> {
    torch::NoGradGuard no_grad;
    const torch::TensorOptions options = conv_in->weight.options();
    torch::Tensor t = timestep.to(options.device()).reshape({-1}).expand({batch});
    return forward(sample.to(options), t, encoder_hidden_states.to(options),
                   controlnet_cond.to(options), conditioning_scale, taps);
  });
}

absl::StatusOr<torch::Tensor> ControlNetModelImpl::RunTimeEmbedding(const torch::Tensor& timestep,
                                                                    int64_t batch) {
  FD_RETURN_IF_ERROR(CheckTimestep(timestep, batch));
  return TorchCall("ControlNet time embedding", [&]() -> absl::StatusOr<torch::Tensor> {
    torch::NoGradGuard no_grad;
    return EmbedTime(timestep.to(conv_in->weight.device()).reshape({-1}).expand({batch}));
  });
}

absl::StatusOr<torch::Tensor> ControlNetModelImpl::RunConditionEmbedding(
    const torch::Tensor& controlnet_cond) {
  const int64_t factor = condition_factor();
  if (!controlnet_cond.defined() || controlnet_cond.dim() != 4 ||
      controlnet_cond.size(1) != config_.ConditionChannels() ||
      controlnet_cond.size(2) % factor != 0 || controlnet_cond.size(3) % factor != 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        "ControlNet: controlnet_cond must be [N, ", config_.ConditionChannels(),
        ", H, W] with H and W multiples of ", factor, ", got ", ShapeOf(controlnet_cond)));
  }
  return TorchCall("ControlNet condition embedding", [&]() -> absl::StatusOr<torch::Tensor> {
    torch::NoGradGuard no_grad;
    return EmbedCondition(controlnet_cond.to(conv_in->weight.options()));
  });
}

absl::StatusOr<std::vector<torch::Tensor>> ControlNetModelImpl::RunEmbedded(
    const torch::Tensor& sample, const torch::Tensor& time_emb,
    const torch::Tensor& encoder_hidden_states, const torch::Tensor& cond_emb,
    double conditioning_scale) {
  FD_RETURN_IF_ERROR(CheckSampleAndText(sample, encoder_hidden_states));
  const int64_t batch = sample.size(0);
  const int64_t c0 = config_.block_out_channels.at(0);
  if (!time_emb.defined() || time_emb.dim() != 2 || time_emb.size(0) != batch ||
      time_emb.size(1) != layout_.time_embed_dim) {
    return absl::InvalidArgumentError(absl::StrCat("ControlNet: time_emb must be [", batch, ", ",
                                                   layout_.time_embed_dim, "], got ",
                                                   ShapeOf(time_emb)));
  }
  if (!cond_emb.defined() || cond_emb.dim() != 4 || cond_emb.size(0) != batch ||
      cond_emb.size(1) != c0 || cond_emb.size(2) != sample.size(2) ||
      cond_emb.size(3) != sample.size(3)) {
    return absl::InvalidArgumentError(absl::StrCat("ControlNet: cond_emb must be [", batch, ", ",
                                                   c0, ", ", sample.size(2), ", ", sample.size(3),
                                                   "], got ", ShapeOf(cond_emb)));
  }
  return TorchCall("ControlNet forward", [&]() -> absl::StatusOr<std::vector<torch::Tensor>> {
    torch::NoGradGuard no_grad;
    const torch::TensorOptions options = conv_in->weight.options();
    return ForwardEmbedded(sample.to(options), time_emb.to(options),
                           encoder_hidden_states.to(options), cond_emb.to(options),
                           conditioning_scale);
  });
}

absl::StatusOr<ControlNetModel> MakeControlNet(const ControlNetConfig& config,
                                               ControlNetEmbeddingKind embedding) {
  FD_ASSIGN_OR_RETURN(UNetLayout layout, ComputeControlNetLayout(config));
  for (const UNetBlockLayout& block : layout.down_blocks) {
    FD_RETURN_IF_ERROR(MakeDownBlock(block.type, {}).status());
  }
  if (layout.mid_block.type != "UNetMidBlock2DCrossAttn") {
    return absl::UnimplementedError(
        absl::StrCat("ControlNet: unsupported mid_block_type '", layout.mid_block.type, "'"));
  }
  const size_t widths = config.conditioning_embedding_out_channels.size();
  if (embedding == ControlNetEmbeddingKind::kFrameDiffuserEx && widths != 4) {
    return absl::InvalidArgumentError(
        absl::StrCat("ControlNetModelEx: conditioning_embedding_out_channels must have 4 "
                     "entries, has ",
                     widths));
  }
  if (widths == 0) {
    return absl::InvalidArgumentError("ControlNet: conditioning_embedding_out_channels is empty");
  }
  return TorchCall("MakeControlNet", [&]() -> absl::StatusOr<ControlNetModel> {
    return ControlNetModel(config, layout, embedding);
  });
}

absl::StatusOr<ControlNetModel> LoadControlNet(const std::string& dir, torch::Device device,
                                               torch::Dtype dtype, const FileSource& files) {
  FD_ASSIGN_OR_RETURN(ControlNetConfig config, LoadControlNetConfig(dir + "/config.json", files));
  FD_ASSIGN_OR_RETURN(std::unique_ptr<SafetensorsFile> file,
                      files.OpenSafetensors(dir + "/diffusion_pytorch_model.safetensors"));
  const ControlNetEmbeddingKind kind = DetectControlNetEmbedding(config, file->Keys());
  FD_ASSIGN_OR_RETURN(ControlNetModel controlnet, MakeControlNet(config, kind));
  FD_RETURN_IF_ERROR(LoadStateDict(*controlnet, *file));
  FD_RETURN_IF_ERROR(MoveModule(*controlnet, device, dtype));
  return controlnet;
}

}  // namespace fd::model

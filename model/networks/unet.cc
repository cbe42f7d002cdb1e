// Port of diffusers v0.31.0 UNet2DConditionModel.forward
// (src/diffusers/models/unets/unet_2d_condition.py) for the SD1.5 family;
// see unet.h.
#include "model/networks/unet.h"

#include <torch/torch.h>

#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "base/status_macros.h"
#include "model/checkpoint/checkpoint_loading.h"
#include "model/checkpoint/safetensors.h"
#include "model/checkpoint/state_dict_loader.h"
#include "model/runtime/torch_call.h"

namespace fd::model {
namespace {

std::string ShapeOf(const torch::Tensor& t) {
  if (!t.defined()) return "undefined";
  return absl::StrCat("[", absl::StrJoin(t.sizes().vec(), ", "), "]");
}

// The ControlNet residuals in the model's dtype and device.
std::vector<torch::Tensor> ToOptions(const std::vector<torch::Tensor>& control,
                                     const torch::TensorOptions& options) {
  std::vector<torch::Tensor> out;
  out.reserve(control.size());
  for (const torch::Tensor& r : control) out.push_back(r.to(options));
  return out;
}

}  // namespace

UNet2DConditionModelImpl::UNet2DConditionModelImpl(const UNet2DConditionConfig& config,
                                                   const UNetLayout& layout)
    : config_(config), layout_(layout) {
  namespace nn = torch::nn;
  const int64_t c0 = config.block_out_channels.at(0);
  const int64_t temb = layout.time_embed_dim;
  conv_in = register_module("conv_in", LoraConv2d(config.InputChannels(), c0, config.conv_in_kernel,
                                                  1, (config.conv_in_kernel - 1) / 2));
  time_proj = register_module(
      "time_proj", Timesteps(c0, config.flip_sin_to_cos, static_cast<double>(config.freq_shift)));
  time_embedding = register_module("time_embedding", TimestepEmbedding(c0, temb));

  down_blocks = register_module("down_blocks", nn::ModuleList());
  for (const UNetBlockLayout& block : layout.down_blocks) {
    down_blocks_.push_back(
        MakeDownBlock(block.type, BlockOptionsFromLayout(config, block, temb)).value());
    down_blocks->push_back(down_blocks_.back());
  }

  UNetBlockOptions mid = BlockOptionsFromLayout(config, layout.mid_block, temb);
  mid.output_scale_factor = config.mid_block_scale_factor;
  mid_block = register_module("mid_block", UNetMidBlock2DCrossAttn(mid));

  up_blocks = register_module("up_blocks", nn::ModuleList());
  for (const UNetBlockLayout& block : layout.up_blocks) {
    up_blocks_.push_back(
        MakeUpBlock(block.type, BlockOptionsFromLayout(config, block, temb)).value());
    up_blocks->push_back(up_blocks_.back());
    if (block.add_sampler) overall_up_factor_ *= 2;
  }

  conv_norm_out = register_module(
      "conv_norm_out",
      nn::GroupNorm(nn::GroupNormOptions(config.norm_num_groups, c0).eps(config.norm_eps)));
  conv_out = register_module("conv_out", LoraConv2d(c0, config.out_channels, config.conv_out_kernel,
                                                    1, (config.conv_out_kernel - 1) / 2));
}

int64_t UNet2DConditionModelImpl::num_down_residuals() const {
  int64_t n = 1;  // conv_in output
  for (const UNetBlockLayout& block : layout_.down_blocks) {
    n += block.num_layers + (block.add_sampler ? 1 : 0);
  }
  return n;
}

std::vector<std::vector<int64_t>> UNet2DConditionModelImpl::ResidualShapes(int64_t batch,
                                                                           int64_t height,
                                                                           int64_t width) const {
  std::vector<std::vector<int64_t>> shapes = {
      {batch, config_.block_out_channels.at(0), height, width}};
  for (const UNetBlockLayout& block : layout_.down_blocks) {
    for (int64_t i = 0; i < block.num_layers; ++i) {
      shapes.push_back({batch, block.out_channels, height, width});
    }
    if (block.add_sampler) {
      // Downsample2D: 3x3 conv, stride 2, padding 1 -> ceil(size / 2).
      height = (height + 1) / 2;
      width = (width + 1) / 2;
      shapes.push_back({batch, block.out_channels, height, width});
    }
  }
  shapes.push_back({batch, layout_.mid_block.out_channels, height, width});
  return shapes;
}

torch::Tensor UNet2DConditionModelImpl::forward(const torch::Tensor& sample,
                                                const torch::Tensor& timesteps,
                                                const torch::Tensor& encoder_hidden_states,
                                                const std::vector<torch::Tensor>& control,
                                                DebugTaps* taps) {
  // 1. time, [N, 4*C0]
  torch::Tensor emb = EmbedTime(timesteps);
  if (taps != nullptr) {
    (*taps)["time_proj"] = time_proj(timesteps).to(sample.scalar_type());
    (*taps)["time_embedding"] = emb;
  }
  return ForwardEmbedded(sample, emb, encoder_hidden_states, control, taps);
}

torch::Tensor UNet2DConditionModelImpl::EmbedTime(const torch::Tensor& timesteps) {
  // [N] -> [N, C0] -> [N, 4*C0]
  const torch::Tensor t_emb = time_proj(timesteps).to(conv_in->weight.scalar_type());
  return time_embedding(t_emb);
}

torch::Tensor UNet2DConditionModelImpl::ForwardEmbedded(const torch::Tensor& sample,
                                                        const torch::Tensor& time_emb,
                                                        const torch::Tensor& encoder_hidden_states,
                                                        const std::vector<torch::Tensor>& control,
                                                        DebugTaps* taps) {
  return ForwardUp(ForwardDown(sample, time_emb, encoder_hidden_states, taps), time_emb,
                   encoder_hidden_states, control, taps);
}

UNet2DConditionModelImpl::DownPath UNet2DConditionModelImpl::ForwardDown(
    const torch::Tensor& sample, const torch::Tensor& time_emb,
    const torch::Tensor& encoder_hidden_states, DebugTaps* taps) {
  const torch::Tensor& emb = time_emb;  // [N, 4*C0]
  DownPath down;
  down.sample_height = sample.size(-2);
  down.sample_width = sample.size(-1);

  // 2. pre-process
  torch::Tensor h = conv_in(sample);  // [N, C0, h, w]
  Tap(taps, "conv_in", h);

  // 3. down
  down.res_samples = {h};
  for (size_t k = 0; k < down_blocks_.size(); ++k) {
    DownBlockOutput out = down_blocks_[k]->Forward(h, emb, encoder_hidden_states);
    h = out.hidden_states;
    if (taps != nullptr) {
      (*taps)[absl::StrCat("down_blocks.", k, ".hidden_states")] = h;
      for (size_t j = 0; j < out.res_samples.size(); ++j) {
        (*taps)[absl::StrCat("down_blocks.", k, ".res_samples.", j)] = out.res_samples[j];
      }
    }
    for (torch::Tensor& r : out.res_samples) down.res_samples.push_back(std::move(r));
  }

  // 4. mid
  down.hidden_states = mid_block(h, emb, encoder_hidden_states);  // [N, C_last, h', w']
  Tap(taps, "mid_block", down.hidden_states);
  return down;
}

torch::Tensor UNet2DConditionModelImpl::ForwardUp(DownPath down, const torch::Tensor& time_emb,
                                                  const torch::Tensor& encoder_hidden_states,
                                                  const std::vector<torch::Tensor>& control,
                                                  DebugTaps* taps) {
  const torch::Tensor& emb = time_emb;  // [N, 4*C0]
  // When h or w is not a multiple of the overall upsampling factor, every
  // upsampler is told the size of its skip tensor.
  bool forward_upsample_size = false;
  for (int64_t dim : {down.sample_height, down.sample_width}) {
    if (dim % overall_up_factor_ != 0) forward_upsample_size = true;
  }
  std::vector<torch::Tensor>& res_samples = down.res_samples;
  torch::Tensor h = std::move(down.hidden_states);  // [N, C_last, h', w']
  // The ControlNet residuals: skip tensors first, then the mid block's output.
  if (!control.empty()) {
    for (size_t i = 0; i < res_samples.size(); ++i) res_samples[i] = res_samples[i] + control[i];
    h = h + control.back();
  }

  // 5. up
  for (size_t k = 0; k < up_blocks_.size(); ++k) {
    const bool is_final_block = k + 1 == up_blocks_.size();
    const size_t n = static_cast<size_t>(up_blocks_[k]->num_resnets());
    std::vector<torch::Tensor> block_res(res_samples.end() - n, res_samples.end());
    res_samples.resize(res_samples.size() - n);
    std::vector<int64_t> upsample_size;
    if (!is_final_block && forward_upsample_size) {
      upsample_size = {res_samples.back().size(2), res_samples.back().size(3)};
    }
    h = up_blocks_[k]->Forward(h, std::move(block_res), emb, encoder_hidden_states, upsample_size);
    Tap(
        taps, [k] { return absl::StrCat("up_blocks.", k); }, h);
  }

  // 6. post-process
  h = conv_norm_out(h);  // [N, C0, h, w]
  Tap(taps, "conv_norm_out", h);
  h = conv_out(torch::silu(h));  // [N, out, h, w]
  Tap(taps, "conv_out", h);
  return h;
}

absl::Status UNet2DConditionModelImpl::CheckInputs(
    const torch::Tensor& sample, const torch::Tensor& encoder_hidden_states,
    const std::vector<torch::Tensor>& control) const {
  if (!sample.defined() || sample.dim() != 4 || sample.size(1) != input_channels()) {
    return absl::InvalidArgumentError(absl::StrCat("UNet: sample must be [N, ", input_channels(),
                                                   ", h, w], got ", ShapeOf(sample)));
  }
  const int64_t batch = sample.size(0);
  const int64_t cross_dim = layout_.mid_block.cross_attention_dim;
  if (!encoder_hidden_states.defined() || encoder_hidden_states.dim() != 3 ||
      encoder_hidden_states.size(0) != batch || encoder_hidden_states.size(2) != cross_dim) {
    return absl::InvalidArgumentError(absl::StrCat("UNet: encoder_hidden_states must be [", batch,
                                                   ", L, ", cross_dim, "], got ",
                                                   ShapeOf(encoder_hidden_states)));
  }
  return CheckControl(batch, sample.size(2), sample.size(3), control);
}

absl::Status UNet2DConditionModelImpl::CheckControl(
    int64_t batch, int64_t height, int64_t width, const std::vector<torch::Tensor>& control) const {
  if (!control.empty()) {
    const std::vector<std::vector<int64_t>> shapes = ResidualShapes(batch, height, width);
    if (control.size() != shapes.size()) {
      return absl::InvalidArgumentError(
          absl::StrCat("UNet: expected ", shapes.size() - 1,
                       " ControlNet down residuals + 1 mid residual, got ", control.size()));
    }
    for (size_t i = 0; i < shapes.size(); ++i) {
      if (!control[i].defined() || control[i].sizes() != torch::IntArrayRef(shapes[i])) {
        return absl::InvalidArgumentError(absl::StrCat(
            "UNet: ControlNet residual ", i, i + 1 == shapes.size() ? " (mid)" : "", " must be [",
            absl::StrJoin(shapes[i], ", "), "], got ", ShapeOf(control[i])));
      }
    }
  }
  return absl::OkStatus();
}

namespace {

absl::Status CheckUNetTimestep(const torch::Tensor& timestep, int64_t batch) {
  if (!timestep.defined() || timestep.dim() > 1 ||
      (timestep.dim() == 1 && timestep.size(0) != 1 && timestep.size(0) != batch)) {
    return absl::InvalidArgumentError(absl::StrCat("UNet: timestep must be a scalar, [1] or [",
                                                   batch, "], got ", ShapeOf(timestep)));
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<torch::Tensor> UNet2DConditionModelImpl::Run(
    const torch::Tensor& sample, const torch::Tensor& timestep,
    const torch::Tensor& encoder_hidden_states, const std::vector<torch::Tensor>& control,
    DebugTaps* taps) {
  FD_RETURN_IF_ERROR(CheckInputs(sample, encoder_hidden_states, control));
  const int64_t batch = sample.size(0);
  FD_RETURN_IF_ERROR(CheckUNetTimestep(timestep, batch));
  return TorchCall("UNet forward", [&]() -> absl::StatusOr<torch::Tensor> {
    torch::NoGradGuard no_grad;
    const torch::TensorOptions options = conv_in->weight.options();
    // diffusers: a 0-d timestep gets a batch dim, then expand(batch).
    torch::Tensor t = timestep.to(options.device()).reshape({-1}).expand({batch});
    std::vector<torch::Tensor> residuals;
    residuals.reserve(control.size());
    for (const torch::Tensor& r : control) residuals.push_back(r.to(options));
    return forward(sample.to(options), t, encoder_hidden_states.to(options), residuals, taps);
  });
}

absl::StatusOr<torch::Tensor> UNet2DConditionModelImpl::RunTimeEmbedding(
    const torch::Tensor& timestep, int64_t batch) {
  FD_RETURN_IF_ERROR(CheckUNetTimestep(timestep, batch));
  return TorchCall("UNet time embedding", [&]() -> absl::StatusOr<torch::Tensor> {
    torch::NoGradGuard no_grad;
    return EmbedTime(timestep.to(conv_in->weight.device()).reshape({-1}).expand({batch}));
  });
}

absl::StatusOr<torch::Tensor> UNet2DConditionModelImpl::RunEmbedded(
    const torch::Tensor& sample, const torch::Tensor& time_emb,
    const torch::Tensor& encoder_hidden_states, const std::vector<torch::Tensor>& control) {
  FD_RETURN_IF_ERROR(CheckInputs(sample, encoder_hidden_states, control));
  FD_RETURN_IF_ERROR(CheckTimeEmbedding(time_emb, sample.size(0)));
  return TorchCall("UNet forward", [&]() -> absl::StatusOr<torch::Tensor> {
    torch::NoGradGuard no_grad;
    const torch::TensorOptions options = conv_in->weight.options();
    return ForwardEmbedded(sample.to(options), time_emb.to(options),
                           encoder_hidden_states.to(options), ToOptions(control, options));
  });
}

absl::StatusOr<UNet2DConditionModelImpl::DownPath> UNet2DConditionModelImpl::RunDown(
    const torch::Tensor& sample, const torch::Tensor& time_emb,
    const torch::Tensor& encoder_hidden_states) {
  FD_RETURN_IF_ERROR(CheckInputs(sample, encoder_hidden_states, {}));
  FD_RETURN_IF_ERROR(CheckTimeEmbedding(time_emb, sample.size(0)));
  return TorchCall("UNet down path", [&]() -> absl::StatusOr<DownPath> {
    torch::NoGradGuard no_grad;
    const torch::TensorOptions options = conv_in->weight.options();
    return ForwardDown(sample.to(options), time_emb.to(options), encoder_hidden_states.to(options));
  });
}

absl::StatusOr<torch::Tensor> UNet2DConditionModelImpl::RunUp(
    DownPath down, const torch::Tensor& time_emb, const torch::Tensor& encoder_hidden_states,
    const std::vector<torch::Tensor>& control) {
  if (!down.hidden_states.defined() ||
      static_cast<int64_t>(down.res_samples.size()) != num_down_residuals()) {
    return absl::InvalidArgumentError("UNet: the down path is incomplete (not from RunDown)");
  }
  const int64_t batch = down.hidden_states.size(0);
  if (!encoder_hidden_states.defined() || encoder_hidden_states.dim() != 3 ||
      encoder_hidden_states.size(0) != batch) {
    return absl::InvalidArgumentError(absl::StrCat("UNet: encoder_hidden_states must be [", batch,
                                                   ", L, D], got ",
                                                   ShapeOf(encoder_hidden_states)));
  }
  FD_RETURN_IF_ERROR(CheckControl(batch, down.sample_height, down.sample_width, control));
  FD_RETURN_IF_ERROR(CheckTimeEmbedding(time_emb, batch));
  return TorchCall("UNet up path", [&]() -> absl::StatusOr<torch::Tensor> {
    torch::NoGradGuard no_grad;
    const torch::TensorOptions options = conv_in->weight.options();
    return ForwardUp(std::move(down), time_emb.to(options), encoder_hidden_states.to(options),
                     ToOptions(control, options));
  });
}

absl::Status UNet2DConditionModelImpl::CheckTimeEmbedding(const torch::Tensor& time_emb,
                                                          int64_t batch) const {
  if (!time_emb.defined() || time_emb.dim() != 2 || time_emb.size(0) != batch ||
      time_emb.size(1) != layout_.time_embed_dim) {
    return absl::InvalidArgumentError(absl::StrCat("UNet: time_emb must be [", batch, ", ",
                                                   layout_.time_embed_dim, "], got ",
                                                   ShapeOf(time_emb)));
  }
  return absl::OkStatus();
}

absl::StatusOr<UNet2DConditionModel> MakeUNet(const UNet2DConditionConfig& config) {
  FD_ASSIGN_OR_RETURN(UNetLayout layout, ComputeUNetLayout(config));
  for (const UNetBlockLayout& block : layout.down_blocks) {
    FD_RETURN_IF_ERROR(MakeDownBlock(block.type, {}).status());
  }
  for (const UNetBlockLayout& block : layout.up_blocks) {
    FD_RETURN_IF_ERROR(MakeUpBlock(block.type, {}).status());
  }
  if (layout.mid_block.type != "UNetMidBlock2DCrossAttn") {
    return absl::UnimplementedError(
        absl::StrCat("UNet: unsupported mid_block_type '", layout.mid_block.type, "'"));
  }
  return TorchCall("MakeUNet", [&]() -> absl::StatusOr<UNet2DConditionModel> {
    return UNet2DConditionModel(config, layout);
  });
}

absl::StatusOr<UNet2DConditionModel> LoadUNet(const std::string& dir, torch::Device device,
                                              torch::Dtype dtype, bool frame_diffuser_input,
                                              const FileSource& files) {
  FD_ASSIGN_OR_RETURN(UNet2DConditionConfig config,
                      LoadUNet2DConditionConfig(dir + "/config.json", files));
  const std::string weights_path = dir + "/diffusion_pytorch_model.safetensors";
  FD_ASSIGN_OR_RETURN(std::unique_ptr<SafetensorsFile> file, files.OpenSafetensors(weights_path));
  FD_ASSIGN_OR_RETURN(SafetensorsFile::TensorInfo conv_in_info, file->Info("conv_in.weight"));
  FD_ASSIGN_OR_RETURN(int64_t weight_channels, InferConvInChannels(config, conv_in_info.shape));
  // UNet2DConditionModelEx.add_extra_conditions(["gbuffer"]): noisy latent +
  // previous-frame latent, both out_channels wide (+ the basecolor patches
  // when the config has them); a base UNet's conv_in is zero-padded to that.
  const int64_t wanted =
      frame_diffuser_input ? config.FrameDiffuserInputChannels() : weight_channels;
  if (weight_channels != wanted && weight_channels != config.out_channels) {
    return absl::InvalidArgumentError(
        absl::StrCat(weights_path, ": conv_in.weight has ", weight_channels,
                     " input channels; a FrameDiffuser UNet needs ", wanted, " (or ",
                     config.out_channels, ", zero-padded)",
                     config.basecolor_patch_channels > 0
                         ? absl::StrCat(": config.json's basecolor_patch_channels is ",
                                        config.basecolor_patch_channels)
                         : ""));
  }
  config.conv_in_channels = wanted;
  FD_ASSIGN_OR_RETURN(UNet2DConditionModel unet, MakeUNet(config));
  LoadOptions options;
  options.adapt_shape = [wanted](const std::string& name, torch::Tensor loaded,
                                 const torch::Tensor& target) -> absl::StatusOr<torch::Tensor> {
    if (name != "conv_in.weight" || loaded.dim() != 4 || loaded.size(1) >= wanted) return loaded;
    // add_extra_conditions: the extra input channels start at zero.
    torch::Tensor padded = torch::zeros(target.sizes(), loaded.options());
    padded.slice(1, 0, loaded.size(1)).copy_(loaded);
    return padded;
  };
  FD_RETURN_IF_ERROR(LoadStateDict(*unet, *file, options));
  FD_RETURN_IF_ERROR(MoveModule(*unet, device, dtype));
  return unet;
}

}  // namespace fd::model

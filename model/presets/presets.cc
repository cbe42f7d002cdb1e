// Random-weight FrameDiffuser checkpoints; see checkpoint_maker.h.
#include "model/presets/presets.h"

#include <ATen/CPUGeneratorImpl.h>
#include <torch/torch.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <utility>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "base/status_macros.h"
#include "model/checkpoint/checkpoint_writer.h"
#include "model/checkpoint/safetensors.h"
#include "model/lora/lora_layers.h"
#include "model/networks/controlnet.h"
#include "model/networks/model_configs.h"
#include "model/networks/unet.h"
#include "model/networks/vae.h"
#include "model/runtime/torch_call.h"

namespace fd::model {
namespace {

using Json = nlohmann::json;
namespace fs = std::filesystem;

// The shapes a preset varies; everything else is SD1.5's.
struct PresetShape {
  std::vector<int64_t> unet_channels;
  std::vector<std::string> down_blocks;
  std::vector<std::string> up_blocks;
  int64_t layers_per_block;
  int64_t cross_attention_dim;
  int64_t attention_heads;  // attention_head_dim in SD1.5's (quirky) sense
  int64_t norm_num_groups;
  int64_t sample_size;  // latent size
  std::vector<int64_t> controlnet_embedding_channels;
  std::vector<int64_t> vae_channels;
  int64_t vae_layers_per_block;
  int64_t vae_norm_num_groups;
  int64_t lora_rank;
  int64_t latent_channels = 4;  // SD1.5's; the VAE latent and the UNet's in/out
};

const std::vector<std::string> kSd15Down = {"CrossAttnDownBlock2D", "CrossAttnDownBlock2D",
                                            "CrossAttnDownBlock2D", "DownBlock2D"};
const std::vector<std::string> kSd15Up = {"UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D",
                                          "CrossAttnUpBlock2D"};

const std::map<std::string, PresetShape>& Presets() {
  static const auto* presets = new std::map<std::string, PresetShape>{
      {"tiny",
       {{16, 32},
        {"CrossAttnDownBlock2D", "DownBlock2D"},
        {"UpBlock2D", "CrossAttnUpBlock2D"},
        1,
        32,
        4,
        8,
        8,
        {8, 16, 16, 32},
        {8, 16, 16, 16},
        1,
        4,
        4}},
      {"small",
       {{32, 64, 128, 128},
        kSd15Down,
        kSd15Up,
        2,
        128,
        8,
        16,
        32,
        {16, 32, 96, 128},
        {32, 64, 128, 128},
        2,
        16,
        8}},
      // The shipped environments' widths (docs/EVALUATION.md says how they
      // were chosen): three UNet levels over a 16x16 latent at 128x128 and
      // SD's 4-channel latent at 8x downsampling (the authors' ControlNet-Ex
      // encoder). 16 channels reconstructed 0.6 dB better but left most of
      // the latent's variance as posterior noise, and the denoiser trained
      // on it learned nothing in the same steps.
      {"compact",
       {{32, 64, 128},
        {"CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"},
        {"UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"},
        2,
        64,
        8,
        32,
        16,
        {16, 32, 96, 128},
        {32, 64, 128, 128},
        2,
        16,
        8,
        4}},
      // runwayml/stable-diffusion-v1-5 unet/vae config.json, the
      // ControlNetModelEx.from_unet embedding widths, train_3_stages.bat rank.
      {"sd15",
       {{320, 640, 1280, 1280},
        kSd15Down,
        kSd15Up,
        2,
        768,
        8,
        32,
        64,
        {16, 32, 96, 256},
        {128, 256, 512, 512},
        2,
        32,
        64}},
  };
  return *presets;
}

// The keys diffusers v0.31 writes for UNet2DConditionModel / ControlNetModel
// (SD1.5 values), plus the preset's shapes.
Json UNetCommonJson(const PresetShape& p) {
  return Json{{"_diffusers_version", "0.31.0"},
              {"act_fn", "silu"},
              {"addition_embed_type", nullptr},
              {"addition_embed_type_num_heads", 64},
              {"addition_time_embed_dim", nullptr},
              {"attention_head_dim", p.attention_heads},
              {"block_out_channels", p.unet_channels},
              {"class_embed_type", nullptr},
              {"cross_attention_dim", p.cross_attention_dim},
              {"down_block_types", p.down_blocks},
              {"downsample_padding", 1},
              {"encoder_hid_dim", nullptr},
              {"encoder_hid_dim_type", nullptr},
              {"flip_sin_to_cos", true},
              {"freq_shift", 0},
              {"in_channels", p.latent_channels},
              {"layers_per_block", p.layers_per_block},
              {"mid_block_scale_factor", 1},
              {"mid_block_type", "UNetMidBlock2DCrossAttn"},
              {"norm_eps", 1e-05},
              {"norm_num_groups", p.norm_num_groups},
              {"num_attention_heads", nullptr},
              {"num_class_embeds", nullptr},
              {"only_cross_attention", false},
              {"projection_class_embeddings_input_dim", nullptr},
              {"resnet_time_scale_shift", "default"},
              {"transformer_layers_per_block", 1},
              {"upcast_attention", false},
              {"use_linear_projection", false}};
}

Json UNetJson(const PresetShape& p) {
  Json j = UNetCommonJson(p);
  j.update(Json{{"_class_name", "UNet2DConditionModelEx"},
                {"attention_type", "default"},
                {"center_input_sample", false},
                {"class_embeddings_concat", false},
                {"conv_in_kernel", 3},
                {"conv_out_kernel", 3},
                {"cross_attention_norm", nullptr},
                {"dropout", 0.0},
                {"dual_cross_attention", false},
                // The base config, as the authors' save_config writes it;
                // the weight has the extended 8-channel conv_in.
                {"extra_condition_names", Json::array()},
                {"mid_block_only_cross_attention", nullptr},
                {"out_channels", p.latent_channels},
                {"resnet_out_scale_factor", 1.0},
                {"resnet_skip_time_act", false},
                {"reverse_transformer_layers_per_block", nullptr},
                {"sample_size", p.sample_size},
                {"time_cond_proj_dim", nullptr},
                {"time_embedding_act_fn", nullptr},
                {"time_embedding_dim", nullptr},
                {"time_embedding_type", "positional"},
                {"timestep_post_act", nullptr},
                {"up_block_types", p.up_blocks}});
  return j;
}

Json ControlNetJson(const PresetShape& p) {
  Json j = UNetCommonJson(p);
  j.update(Json{{"_class_name", "ControlNetModelEx"},
                {"conditioning_channels", 10},
                {"conditioning_embedding_out_channels", p.controlnet_embedding_channels},
                {"controlnet_conditioning_channel_order", "rgb"},
                {"gbuffer_channels", 10},
                {"global_pool_conditions", false}});
  return j;
}

Json VaeJson(const PresetShape& p) {
  const size_t n = p.vae_channels.size();
  return Json{{"_class_name", "AutoencoderKL"},
              {"_diffusers_version", "0.31.0"},
              {"act_fn", "silu"},
              {"block_out_channels", p.vae_channels},
              {"down_block_types", std::vector<std::string>(n, "DownEncoderBlock2D")},
              {"force_upcast", true},
              {"in_channels", 3},
              {"latent_channels", p.latent_channels},
              {"latents_mean", nullptr},
              {"latents_std", nullptr},
              {"layers_per_block", p.vae_layers_per_block},
              {"mid_block_add_attention", true},
              {"norm_num_groups", p.vae_norm_num_groups},
              {"out_channels", 3},
              {"sample_size", p.sample_size * 8},
              {"scaling_factor", 0.18215},
              {"shift_factor", nullptr},
              {"up_block_types", std::vector<std::string>(n, "UpDecoderBlock2D")},
              {"use_post_quant_conv", true},
              {"use_quant_conv", true}};
}

// Fills every parameter of `module` as the golden generators did; fails if a
// parameter belongs to no known layer type (it would otherwise stay zero).
absl::Status Randomize(torch::nn::Module& module, at::Generator& gen) {
  return TorchCall("Randomize", [&]() -> absl::Status {
    torch::NoGradGuard no_grad;
    int64_t filled = 0;
    auto normal = [&](torch::Tensor& t, double mean, double std) {
      t.copy_(torch::randn(t.sizes(), gen) * std + mean);
      ++filled;
    };
    for (const std::shared_ptr<torch::nn::Module>& m : module.modules(/*include_self=*/true)) {
      if (auto* linear = dynamic_cast<LoraLinearImpl*>(m.get())) {
        normal(linear->weight, 0.0, 1.0 / std::sqrt(static_cast<double>(linear->in_features())));
        if (linear->bias.defined()) normal(linear->bias, 0.0, 0.05);
      } else if (auto* conv = dynamic_cast<LoraConv2dImpl*>(m.get())) {
        const double fan_in =
            static_cast<double>(conv->in_channels() * conv->kernel_size() * conv->kernel_size());
        normal(conv->weight, 0.0, 1.0 / std::sqrt(fan_in));
        if (conv->bias.defined()) normal(conv->bias, 0.0, 0.05);
      } else if (auto* group_norm = dynamic_cast<torch::nn::GroupNormImpl*>(m.get())) {
        normal(group_norm->weight, 1.0, 0.1);
        normal(group_norm->bias, 0.0, 0.1);
      } else if (auto* layer_norm = dynamic_cast<torch::nn::LayerNormImpl*>(m.get())) {
        normal(layer_norm->weight, 1.0, 0.1);
        normal(layer_norm->bias, 0.0, 0.1);
      }
    }
    const int64_t total = static_cast<int64_t>(module.parameters().size());
    if (filled != total) {
      return absl::InternalError(
          absl::StrCat("Randomize: ", total - filled, " parameters of unknown layers"));
    }
    return absl::OkStatus();
  });
}

absl::Status WriteControlLora(torch::nn::Module& unet, int64_t rank, const fs::path& dir,
                              torch::Dtype dtype, at::Generator& gen) {
  std::map<std::string, torch::Tensor> tensors;
  FD_RETURN_IF_ERROR(TorchCall("WriteControlLora", [&]() -> absl::Status {
    const double up_std = 0.3 / std::sqrt(static_cast<double>(rank));
    for (const auto& item : unet.named_modules(/*name_prefix=*/"", /*include_self=*/false)) {
      if (!IsFullSkipAttnTarget(item.key())) continue;
      std::vector<int64_t> down_shape, up_shape;
      if (auto* linear = dynamic_cast<LoraLinearImpl*>(item.value().get())) {
        down_shape = {rank, linear->in_features()};
        up_shape = {linear->out_features(), rank};
      } else if (auto* conv = dynamic_cast<LoraConv2dImpl*>(item.value().get())) {
        down_shape = {rank, conv->in_channels(), conv->kernel_size(), conv->kernel_size()};
        up_shape = {conv->out_channels(), rank, 1, 1};
      } else {
        continue;
      }
      int64_t fan_in = 1;
      for (size_t d = 1; d < down_shape.size(); ++d) fan_in *= down_shape[d];
      const std::string prefix = "unet." + item.key();
      tensors[prefix + ".lora_A.weight"] =
          (torch::randn(down_shape, gen) / std::sqrt(static_cast<double>(fan_in))).to(dtype);
      tensors[prefix + ".lora_B.weight"] = (torch::randn(up_shape, gen) * up_std).to(dtype);
    }
    return absl::OkStatus();
  }));
  FD_RETURN_IF_ERROR(CreateDirectories(dir.string()));
  return WriteSafetensorsFile((dir / "pytorch_lora_weights.safetensors").string(), tensors);
}

}  // namespace

std::vector<std::string> CheckpointPresetNames() { return {"tiny", "small", "compact", "sd15"}; }

absl::StatusOr<PresetConfigs> GetPresetConfigs(const std::string& preset) {
  auto it = Presets().find(preset);
  if (it == Presets().end()) {
    return absl::InvalidArgumentError(
        absl::StrCat("unknown checkpoint preset '", preset,
                     "' (presets: ", absl::StrJoin(CheckpointPresetNames(), ", "), ")"));
  }
  PresetConfigs configs;
  configs.unet = UNetJson(it->second).dump(2) + "\n";
  configs.controlnet = ControlNetJson(it->second).dump(2) + "\n";
  configs.vae = VaeJson(it->second).dump(2) + "\n";
  configs.lora_rank = it->second.lora_rank;
  return configs;
}

absl::Status MakeCheckpoint(const MakeCheckpointOptions& options) {
  FD_ASSIGN_OR_RETURN(PresetConfigs configs, GetPresetConfigs(options.preset));
  if (options.out_dir.empty()) return absl::InvalidArgumentError("no output directory given");
  if (options.dtype != torch::kFloat32 && options.dtype != torch::kFloat16 &&
      options.dtype != torch::kBFloat16) {
    return absl::InvalidArgumentError("dtype must be float32, float16 or bfloat16");
  }
  if (options.lora_rank < 0) return absl::InvalidArgumentError("lora_rank must be >= 0");
  const int64_t rank = options.lora_rank > 0 ? options.lora_rank : configs.lora_rank;
  const fs::path out(options.out_dir);
  at::Generator gen = at::make_generator<at::CPUGeneratorImpl>(options.seed);

  {  // UNet2DConditionModelEx with the extended (noisy + previous latent) conv_in.
    FD_ASSIGN_OR_RETURN(UNet2DConditionConfig config,
                        ParseUNet2DConditionConfig(configs.unet, "unet preset"));
    config.conv_in_channels = 2 * config.out_channels;
    FD_ASSIGN_OR_RETURN(UNet2DConditionModel unet, MakeUNet(config));
    FD_RETURN_IF_ERROR(Randomize(*unet, gen));
    FD_RETURN_IF_ERROR(
        WriteModelFolder(*unet, configs.unet, (out / "unet").string(), options.dtype));
    FD_RETURN_IF_ERROR(WriteControlLora(*unet, rank, out / "controllora", options.dtype, gen));
    FD_RETURN_IF_ERROR(TorchCall("prompt_embeds", [&]() -> absl::Status {
      torch::Tensor embeds =
          torch::randn({1, configs.prompt_tokens, config.cross_attention_dim.at(0)}, gen);
      return WriteSafetensorsFile((out / "prompt_embeds.safetensors").string(),
                                  {{"prompt_embeds", embeds.to(options.dtype)}});
    }));
  }
  {
    FD_ASSIGN_OR_RETURN(ControlNetConfig config,
                        ParseControlNetConfig(configs.controlnet, "controlnet preset"));
    FD_ASSIGN_OR_RETURN(ControlNetModel controlnet,
                        MakeControlNet(config, DetectControlNetEmbedding(config)));
    FD_RETURN_IF_ERROR(Randomize(*controlnet, gen));
    FD_RETURN_IF_ERROR(WriteModelFolder(*controlnet, configs.controlnet,
                                        (out / "controlnet").string(), options.dtype));
  }
  {
    FD_ASSIGN_OR_RETURN(AutoencoderKLConfig config,
                        ParseAutoencoderKLConfig(configs.vae, "vae preset"));
    FD_ASSIGN_OR_RETURN(AutoencoderKL vae, MakeVae(config));
    FD_RETURN_IF_ERROR(Randomize(*vae, gen));
    FD_RETURN_IF_ERROR(WriteModelFolder(*vae, configs.vae, (out / "vae").string(), options.dtype));
  }
  FD_RETURN_IF_ERROR(CreateDirectories((out / "scheduler").string()));
  return WriteFileAtomically((out / "scheduler" / "scheduler_config.json").string(),
                             kSd15SchedulerConfigJson);
}

}  // namespace fd::model

// Training-time construction of fd::model's networks; see training_init.h.
#include "model/presets/training_init.h"

#include <ATen/CPUGeneratorImpl.h>
#include <torch/torch.h>

#include <cmath>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "base/status_macros.h"
#include "model/checkpoint/checkpoint_writer.h"
#include "model/lora/lora_layers.h"
#include "model/networks/model_configs.h"
#include "model/runtime/torch_call.h"

namespace fd::model {
namespace {

// U(-bound, bound) in place, from `gen`.
void FillUniform(torch::Tensor& t, double bound, at::Generator& gen) {
  t.copy_(torch::rand(t.sizes(), gen) * (2.0 * bound) - bound);
}

// Copies every parameter of `from` whose name passes `take` into the
// parameter of the same name in `to`; INVALID_ARGUMENT on a missing name or a
// shape mismatch. Returns how many were copied.
template <typename Take>
absl::StatusOr<int> CopyParameters(torch::nn::Module& from, torch::nn::Module& to, Take&& take) {
  torch::OrderedDict<std::string, torch::Tensor> source = from.named_parameters();
  int copied = 0;
  for (auto& item : to.named_parameters()) {
    if (!take(item.key())) continue;
    const torch::Tensor* value = source.find(item.key());
    if (value == nullptr || value->sizes() != item.value().sizes()) {
      return absl::InvalidArgumentError(
          absl::StrCat("parameter '", item.key(), "' has no counterpart of the same shape"));
    }
    torch::NoGradGuard no_grad;
    item.value().copy_(*value);
    ++copied;
  }
  return copied;
}

bool StartsWithAny(const std::string& name, std::initializer_list<const char*> prefixes) {
  for (const char* prefix : prefixes) {
    if (name.rfind(prefix, 0) == 0) return true;
  }
  return false;
}

// Copies every parameter, requires_grad and live LoRA adapter of `from`
// into `to`, a freshly made module of the same config.
absl::Status CopyInto(torch::nn::Module& from, torch::nn::Module& to) {
  torch::NoGradGuard no_grad;
  const torch::Tensor any = from.parameters().at(0);
  to.to(any.device(), any.scalar_type());
  FD_RETURN_IF_ERROR(CopyParameters(from, to, [](const std::string&) { return true; }).status());
  torch::OrderedDict<std::string, torch::Tensor> source = from.named_parameters();
  for (auto& item : to.named_parameters()) {
    item.value().set_requires_grad(source[item.key()].requires_grad());
  }
  const std::vector<std::shared_ptr<torch::nn::Module>> a = from.modules(), b = to.modules();
  for (size_t i = 0; i < a.size() && i < b.size(); ++i) {
    auto* src = dynamic_cast<LoraAdaptable*>(a[i].get());
    auto* dst = dynamic_cast<LoraAdaptable*>(b[i].get());
    if (src == nullptr || dst == nullptr) continue;
    for (const LiveLoraAdapter& adapter : src->live_adapters()) {
      FD_RETURN_IF_ERROR(dst->AddLiveAdapter(adapter.down.detach().clone(),
                                             adapter.up.detach().clone(), adapter.scaling));
      LiveLoraAdapter& copied = dst->mutable_live_adapters().back();
      copied.down = copied.down.to(adapter.down.scalar_type());
      copied.up = copied.up.to(adapter.up.scalar_type());
      copied.down.set_requires_grad(adapter.down.requires_grad());
      copied.up.set_requires_grad(adapter.up.requires_grad());
    }
    dst->set_lora_scale(src->lora_scale());
  }
  return absl::OkStatus();
}

}  // namespace

absl::Status InitializeDefaultWeights(torch::nn::Module& module, uint64_t seed) {
  return TorchCall("InitializeDefaultWeights", [&]() -> absl::Status {
    torch::NoGradGuard no_grad;
    at::Generator gen = at::make_generator<at::CPUGeneratorImpl>(seed);
    int64_t filled = 0;
    for (const std::shared_ptr<torch::nn::Module>& m : module.modules(/*include_self=*/true)) {
      torch::Tensor* weight = nullptr;
      torch::Tensor* bias = nullptr;
      double fan_in = 0;
      if (auto* linear = dynamic_cast<LoraLinearImpl*>(m.get())) {
        weight = &linear->weight;
        bias = &linear->bias;
        fan_in = static_cast<double>(linear->in_features());
      } else if (auto* conv = dynamic_cast<LoraConv2dImpl*>(m.get())) {
        weight = &conv->weight;
        bias = &conv->bias;
        fan_in =
            static_cast<double>(conv->in_channels() * conv->kernel_size() * conv->kernel_size());
      } else if (auto* group_norm = dynamic_cast<torch::nn::GroupNormImpl*>(m.get())) {
        group_norm->weight.fill_(1.0);
        group_norm->bias.zero_();
        filled += 2;
      } else if (auto* layer_norm = dynamic_cast<torch::nn::LayerNormImpl*>(m.get())) {
        layer_norm->weight.fill_(1.0);
        layer_norm->bias.zero_();
        filled += 2;
      }
      if (weight == nullptr) continue;
      // kaiming_uniform_(a=sqrt(5)): gain sqrt(2 / (1 + 5)), bound =
      // gain * sqrt(3 / fan_in) = 1 / sqrt(fan_in); the bias bound is the same.
      const double bound = 1.0 / std::sqrt(fan_in);
      FillUniform(*weight, bound, gen);
      ++filled;
      if (bias->defined()) {
        FillUniform(*bias, bound, gen);
        ++filled;
      }
    }
    const int64_t total = static_cast<int64_t>(module.parameters().size());
    if (filled != total) {
      return absl::InternalError(absl::StrCat("InitializeDefaultWeights: ", total - filled,
                                              " parameters of unknown layers"));
    }
    return absl::OkStatus();
  });
}

void SetRequiresGrad(torch::nn::Module& module, bool requires_grad) {
  for (torch::Tensor& p : module.parameters()) p.set_requires_grad(requires_grad);
}

absl::StatusOr<std::string> ControlNetConfigJsonFromUNet(
    const std::string& unet_config_json, const std::vector<int64_t>& embedding_channels) {
  nlohmann::json j = nlohmann::json::parse(unet_config_json, nullptr, /*allow_exceptions=*/false);
  if (!j.is_object() || !j.contains("block_out_channels")) {
    return absl::InvalidArgumentError("ControlNetConfigJsonFromUNet: not a UNet config.json");
  }
  // Keys of UNet2DConditionModel that ControlNetModel does not have.
  for (const char* key : {"center_input_sample",
                          "out_channels",
                          "up_block_types",
                          "conv_in_kernel",
                          "conv_out_kernel",
                          "sample_size",
                          "dropout",
                          "dual_cross_attention",
                          "time_cond_proj_dim",
                          "time_embedding_act_fn",
                          "time_embedding_dim",
                          "timestep_post_act",
                          "cross_attention_norm",
                          "mid_block_only_cross_attention",
                          "resnet_out_scale_factor",
                          "resnet_skip_time_act",
                          "reverse_transformer_layers_per_block",
                          "attention_type",
                          "class_embeddings_concat",
                          "extra_condition_names",
                          "basecolor_patch_channels",
                          "time_embedding_type"}) {
    j.erase(key);
  }
  j["_class_name"] = "ControlNetModelEx";
  j["conditioning_channels"] = 10;
  j["gbuffer_channels"] = 10;
  j["conditioning_embedding_out_channels"] = embedding_channels;
  j["controlnet_conditioning_channel_order"] = "rgb";
  j["global_pool_conditions"] = false;
  return j.dump(2) + "\n";
}

absl::StatusOr<ControlNetModel> ControlNetFromUNet(UNet2DConditionModelImpl& unet,
                                                   const ControlNetConfig& config, uint64_t seed) {
  if (unet.input_channels() != config.in_channels) {
    return absl::InvalidArgumentError(
        absl::StrCat("ControlNetFromUNet: the UNet's conv_in takes ", unet.input_channels(),
                     " channels; from_unet needs the base UNet (", config.in_channels, ")"));
  }
  FD_ASSIGN_OR_RETURN(ControlNetModel controlnet,
                      MakeControlNet(config, ControlNetEmbeddingKind::kFrameDiffuserEx));
  FD_RETURN_IF_ERROR(InitializeDefaultWeights(*controlnet, seed));
  return TorchCall("ControlNetFromUNet", [&]() -> absl::StatusOr<ControlNetModel> {
    FD_ASSIGN_OR_RETURN(
        int copied, CopyParameters(unet, *controlnet, [](const std::string& name) {
          return StartsWithAny(name, {"conv_in.", "time_embedding.", "down_blocks.", "mid_block."});
        }));
    if (copied == 0) return absl::InvalidArgumentError("ControlNetFromUNet: nothing copied");
    torch::NoGradGuard no_grad;
    for (auto& item : controlnet->named_parameters()) {
      // zero_module(controlnet_down_blocks / controlnet_mid_block), and
      // ControlNetModelEx zeroes its encoder's last conv (model.py 624-625).
      if (StartsWithAny(item.key(), {"controlnet_down_blocks.", "controlnet_mid_block.",
                                     "controlnet_cond_embedding.16."})) {
        item.value().zero_();
      }
    }
    controlnet->to(unet.conv_in->weight.device(), unet.conv_in->weight.scalar_type());
    return controlnet;
  });
}

absl::StatusOr<UNet2DConditionModel> WidenConvIn(UNet2DConditionModelImpl& unet,
                                                 int64_t basecolor_patch_channels) {
  if (basecolor_patch_channels < 0 || basecolor_patch_channels % 3 != 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("WidenConvIn: basecolor_patch_channels must be 0 or 3 * f * f, got ",
                     basecolor_patch_channels));
  }
  UNet2DConditionConfig config = unet.config();
  config.basecolor_patch_channels = basecolor_patch_channels;
  const int64_t wanted = config.FrameDiffuserInputChannels();
  if (unet.input_channels() != config.out_channels) {
    return absl::InvalidArgumentError("WidenConvIn: conv_in is already widened");
  }
  config.conv_in_channels = wanted;
  FD_ASSIGN_OR_RETURN(UNet2DConditionModel wide, MakeUNet(config));
  return TorchCall("WidenConvIn", [&]() -> absl::StatusOr<UNet2DConditionModel> {
    torch::NoGradGuard no_grad;
    wide->to(unet.conv_in->weight.device(), unet.conv_in->weight.scalar_type());
    FD_RETURN_IF_ERROR(CopyParameters(unet, *wide, [](const std::string& name) {
                         return name != "conv_in.weight";
                       }).status());
    torch::Tensor& w = wide->conv_in->weight;  // [C0, 8 (+ basecolor patches), k, k]
    w.zero_();
    w.slice(1, 0, unet.input_channels()).copy_(unet.conv_in->weight);
    return wide;
  });
}

absl::StatusOr<TrainableLora> AddTrainableControlLora(UNet2DConditionModelImpl& unet, int64_t rank,
                                                      uint64_t seed) {
  if (rank < 1) return absl::InvalidArgumentError("LoRA rank must be >= 1");
  return TorchCall("AddTrainableControlLora", [&]() -> absl::StatusOr<TrainableLora> {
    at::Generator gen = at::make_generator<at::CPUGeneratorImpl>(seed);
    for (const auto& item : unet.named_modules(/*name_prefix=*/"", /*include_self=*/false)) {
      if (!IsFullSkipAttnTarget(item.key())) continue;
      auto* layer = dynamic_cast<LoraAdaptable*>(item.value().get());
      if (layer == nullptr) continue;
      if (layer->has_live_adapters()) {
        return absl::InvalidArgumentError(
            absl::StrCat("module '", item.key(), "' already has a LoRA adapter"));
      }
      std::vector<int64_t> down_shape, up_shape;
      if (auto* linear = dynamic_cast<LoraLinearImpl*>(layer)) {
        down_shape = {rank, linear->in_features()};
        up_shape = {linear->out_features(), rank};
      } else if (auto* conv = dynamic_cast<LoraConv2dImpl*>(layer)) {
        down_shape = {rank, conv->in_channels(), conv->kernel_size(), conv->kernel_size()};
        up_shape = {conv->out_channels(), rank, 1, 1};
      } else {
        continue;
      }
      // PEFT "gaussian": nn.init.normal_(lora_A, std=1/r); zeros_(lora_B).
      torch::Tensor down = torch::randn(down_shape, gen) / static_cast<double>(rank);
      torch::Tensor up = torch::zeros(up_shape);
      FD_RETURN_IF_ERROR(layer->AddLiveAdapter(down, up, /*scaling=*/1.0));
    }
    return TrainableLiveLora(unet);
  });
}

absl::StatusOr<TrainableLora> TrainableLiveLora(UNet2DConditionModelImpl& unet) {
  TrainableLora lora;
  for (const std::shared_ptr<torch::nn::Module>& m : unet.modules(/*include_self=*/false)) {
    auto* layer = dynamic_cast<LoraAdaptable*>(m.get());
    if (layer == nullptr) continue;
    for (LiveLoraAdapter& adapter : layer->mutable_live_adapters()) {
      // Float32 masters whatever the UNet's dtype (the authors cast LoRA to
      // fp32 after accelerate.prepare, train.py 2585-2613).
      if (adapter.down.scalar_type() != torch::kFloat32) {
        adapter.down = adapter.down.to(torch::kFloat32);
        adapter.up = adapter.up.to(torch::kFloat32);
      }
      adapter.down = adapter.down.detach();
      adapter.up = adapter.up.detach();
      adapter.down.set_requires_grad(true);
      adapter.up.set_requires_grad(true);
      lora.down.push_back(adapter.down);
      lora.up.push_back(adapter.up);
    }
  }
  if (lora.down.empty()) return absl::InvalidArgumentError("the UNet has no live LoRA adapters");
  return lora;
}

absl::StatusOr<UNet2DConditionModel> CopyUNet(UNet2DConditionModelImpl& unet) {
  FD_ASSIGN_OR_RETURN(UNet2DConditionModel copy, MakeUNet(unet.config()));
  FD_RETURN_IF_ERROR(TorchCall("CopyUNet", [&] { return CopyInto(unet, *copy); }));
  return copy;
}

absl::StatusOr<ControlNetModel> CopyControlNet(ControlNetModelImpl& controlnet) {
  FD_ASSIGN_OR_RETURN(ControlNetModel copy,
                      MakeControlNet(controlnet.config(), controlnet.embedding_kind()));
  FD_RETURN_IF_ERROR(TorchCall("CopyControlNet", [&] { return CopyInto(controlnet, *copy); }));
  return copy;
}

absl::StatusOr<AutoencoderKL> CopyVae(AutoencoderKLImpl& vae) {
  FD_ASSIGN_OR_RETURN(AutoencoderKL copy, MakeVae(vae.config()));
  FD_RETURN_IF_ERROR(TorchCall("CopyVae", [&] { return CopyInto(vae, *copy); }));
  return copy;
}

}  // namespace fd::model

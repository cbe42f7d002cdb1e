#include "model/text/clip_text_model.h"

#include <torch/torch.h>

#include <cmath>
#include <limits>
#include <utility>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "base/status_macros.h"
#include "model/checkpoint/checkpoint_loading.h"
#include "model/checkpoint/safetensors.h"
#include "model/checkpoint/state_dict_loader.h"
#include "model/runtime/torch_call.h"

namespace fd::model {
namespace {

namespace nn = torch::nn;

nn::LayerNorm MakeLayerNorm(const CLIPTextConfig& config) {
  return nn::LayerNorm(nn::LayerNormOptions({config.hidden_size})
                           .eps(config.layer_norm_eps)
                           .elementwise_affine(true));
}

// transformers' _make_causal_mask: 0 on and below the diagonal, the dtype's
// lowest finite value above it. [L, L]
torch::Tensor CausalMask(int64_t length, const torch::TensorOptions& options) {
  const double lowest = options.dtype() == torch::kFloat64   ? std::numeric_limits<double>::lowest()
                        : options.dtype() == torch::kFloat16 ? -65504.0
                        : options.dtype() == torch::kBFloat16
                            ? -3.3895313892515355e38
                            : static_cast<double>(std::numeric_limits<float>::lowest());
  return torch::full({length, length}, lowest, options).triu(1);
}

}  // namespace

ClipAttentionImpl::ClipAttentionImpl(const CLIPTextConfig& config)
    : num_heads_(config.num_attention_heads),
      head_dim_(config.HeadDim()),
      scale_(std::pow(static_cast<double>(config.HeadDim()), -0.5)) {
  const int64_t h = config.hidden_size;
  k_proj = register_module("k_proj", nn::Linear(h, h));
  v_proj = register_module("v_proj", nn::Linear(h, h));
  q_proj = register_module("q_proj", nn::Linear(h, h));
  out_proj = register_module("out_proj", nn::Linear(h, h));
}

torch::Tensor ClipAttentionImpl::forward(const torch::Tensor& x, const torch::Tensor& causal_mask,
                                         DebugTaps* taps, const std::string& prefix) {
  // x: [N, L, H]
  const int64_t n = x.size(0);
  const int64_t len = x.size(1);
  const int64_t h = x.size(2);
  const torch::Tensor q_raw = q_proj(x);
  const torch::Tensor k_raw = k_proj(x);
  const torch::Tensor v_raw = v_proj(x);
  Tap(
      taps, [&] { return prefix + ".q_proj"; }, q_raw);
  Tap(
      taps, [&] { return prefix + ".k_proj"; }, k_raw);
  Tap(
      taps, [&] { return prefix + ".v_proj"; }, v_raw);
  // [N, L, H] -> [N * heads, L, head_dim], query scaled before the product.
  auto heads = [&](const torch::Tensor& t) {
    return t.view({n, len, num_heads_, head_dim_})
        .transpose(1, 2)
        .contiguous()
        .view({n * num_heads_, len, head_dim_});
  };
  const torch::Tensor q = heads(q_raw * scale_);
  const torch::Tensor k = heads(k_raw);
  const torch::Tensor v = heads(v_raw);
  torch::Tensor weights = torch::bmm(q, k.transpose(1, 2));  // [N * heads, L, L]
  weights =
      (weights.view({n, num_heads_, len, len}) + causal_mask).view({n * num_heads_, len, len});
  weights = torch::softmax(weights, -1);
  torch::Tensor out = torch::bmm(weights, v);  // [N * heads, L, head_dim]
  out = out.view({n, num_heads_, len, head_dim_}).transpose(1, 2).reshape({n, len, h});
  out = out_proj(out);
  Tap(
      taps, [&] { return prefix; }, out);
  return out;  // [N, L, H]
}

ClipMlpImpl::ClipMlpImpl(const CLIPTextConfig& config)
    : quick_gelu_(config.hidden_act == "quick_gelu") {
  fc1 = register_module("fc1", nn::Linear(config.hidden_size, config.intermediate_size));
  fc2 = register_module("fc2", nn::Linear(config.intermediate_size, config.hidden_size));
}

torch::Tensor ClipMlpImpl::forward(const torch::Tensor& x, DebugTaps* taps,
                                   const std::string& prefix) {
  // x: [N, L, H]
  torch::Tensor hidden = fc1(x);  // [N, L, intermediate]
  Tap(
      taps, [&] { return prefix + ".fc1"; }, hidden);
  // QuickGELUActivation: input * sigmoid(1.702 * input)
  hidden = quick_gelu_ ? hidden * torch::sigmoid(1.702 * hidden) : torch::gelu(hidden);
  torch::Tensor out = fc2(hidden);
  Tap(
      taps, [&] { return prefix; }, out);
  return out;  // [N, L, H]
}

ClipEncoderLayerImpl::ClipEncoderLayerImpl(const CLIPTextConfig& config) {
  self_attn = register_module("self_attn", ClipAttention(config));
  layer_norm1 = register_module("layer_norm1", MakeLayerNorm(config));
  mlp = register_module("mlp", ClipMlp(config));
  layer_norm2 = register_module("layer_norm2", MakeLayerNorm(config));
}

torch::Tensor ClipEncoderLayerImpl::forward(const torch::Tensor& x,
                                            const torch::Tensor& causal_mask, DebugTaps* taps,
                                            const std::string& prefix) {
  // x: [N, L, H]
  torch::Tensor hidden = layer_norm1(x);
  Tap(
      taps, [&] { return prefix + ".layer_norm1"; }, hidden);
  hidden = x + self_attn(hidden, causal_mask, taps, prefix + ".self_attn");
  torch::Tensor normed = layer_norm2(hidden);
  Tap(
      taps, [&] { return prefix + ".layer_norm2"; }, normed);
  return hidden + mlp(normed, taps, prefix + ".mlp");  // [N, L, H]
}

ClipTextEmbeddingsImpl::ClipTextEmbeddingsImpl(const CLIPTextConfig& config) {
  token_embedding =
      register_module("token_embedding", nn::Embedding(config.vocab_size, config.hidden_size));
  position_embedding = register_module(
      "position_embedding", nn::Embedding(config.max_position_embeddings, config.hidden_size));
  position_ids = register_buffer(
      "position_ids", torch::arange(config.max_position_embeddings, torch::kInt64).unsqueeze(0));
}

torch::Tensor ClipTextEmbeddingsImpl::forward(const torch::Tensor& input_ids) {
  // input_ids: [N, L]
  const int64_t len = input_ids.size(1);
  // Positions are always 0..L-1 (SD1.5); the stored position_ids buffer is
  // that range and is not trusted beyond it.
  const torch::Tensor positions = torch::arange(len, input_ids.options().dtype(torch::kInt64));
  return token_embedding(input_ids) + position_embedding(positions).unsqueeze(0);  // [N, L, H]
}

ClipEncoderImpl::ClipEncoderImpl(const CLIPTextConfig& config) {
  layers = register_module("layers", nn::ModuleList());
  for (int64_t i = 0; i < config.num_hidden_layers; ++i) {
    layer_list.push_back(ClipEncoderLayer(config));
    layers->push_back(layer_list.back());
  }
}

ClipTextTransformerImpl::ClipTextTransformerImpl(const CLIPTextConfig& config) : config_(config) {
  embeddings = register_module("embeddings", ClipTextEmbeddings(config));
  encoder = register_module("encoder", ClipEncoder(config));
  final_layer_norm = register_module("final_layer_norm", MakeLayerNorm(config));
}

ClipTextOutput ClipTextTransformerImpl::forward(const torch::Tensor& input_ids, DebugTaps* taps) {
  // input_ids: [N, L]
  ClipTextOutput out;
  torch::Tensor hidden = embeddings(input_ids);  // [N, L, H]
  const torch::Tensor mask = CausalMask(input_ids.size(1), hidden.options());
  out.hidden_states.push_back(hidden);
  for (size_t i = 0; i < encoder->layer_list.size(); ++i) {
    hidden = encoder->layer_list[i](hidden, mask, taps, "encoder.layers." + std::to_string(i));
    out.hidden_states.push_back(hidden);
  }
  out.last_hidden_state = final_layer_norm(hidden);  // [N, L, H]
  // Pooling at the eos token. With the historic eos_token_id == 2 (SD1.5's
  // config) transformers takes argmax(input_ids): the first occurrence of the
  // largest id, which is <|endoftext|> = 49407.
  const torch::Tensor eos_position =
      config_.eos_token_id == 2 ? input_ids.to(torch::kInt32).argmax(-1)
                                : input_ids.eq(config_.eos_token_id).to(torch::kInt32).argmax(-1);
  out.pooler_output = out.last_hidden_state.index(
      {torch::arange(input_ids.size(0), eos_position.options().dtype(torch::kInt64)),
       eos_position.to(torch::kInt64)});  // [N, H]
  return out;
}

ClipTextModelImpl::ClipTextModelImpl(const CLIPTextConfig& config) : config_(config) {
  text_model = register_module("text_model", ClipTextTransformer(config));
}

ClipTextOutput ClipTextModelImpl::forward(const torch::Tensor& input_ids, DebugTaps* taps) {
  return text_model(input_ids, taps);
}

absl::StatusOr<ClipTextOutput> ClipTextModelImpl::Run(const torch::Tensor& input_ids,
                                                      DebugTaps* taps) {
  return TorchCall("ClipTextModel::Run", [&]() -> absl::StatusOr<ClipTextOutput> {
    if (!input_ids.defined() || input_ids.dim() != 2 || input_ids.is_floating_point() ||
        input_ids.scalar_type() == torch::kBool) {
      return absl::InvalidArgumentError(
          "input_ids: must be an integer tensor [N, L]" +
          (input_ids.defined()
               ? absl::StrCat(", got ", std::string(c10::toString(input_ids.scalar_type())), " [",
                              absl::StrJoin(input_ids.sizes(), ", "), "]")
               : std::string()));
    }
    const int64_t len = input_ids.size(1);
    if (input_ids.size(0) < 1 || len < 1 || len > config_.max_position_embeddings) {
      return absl::InvalidArgumentError(absl::StrCat(
          "input_ids: need N >= 1 and 1 <= L <= max_position_embeddings (",
          config_.max_position_embeddings, "), got [", input_ids.size(0), ", ", len, "]"));
    }
    const torch::Tensor ids = input_ids.to(torch::kInt64);
    const int64_t min_id = ids.min().item<int64_t>();
    const int64_t max_id = ids.max().item<int64_t>();
    if (min_id < 0 || max_id >= config_.vocab_size) {
      return absl::InvalidArgumentError(absl::StrCat("input_ids: ids must be in [0, ",
                                                     config_.vocab_size, "), got [", min_id, ", ",
                                                     max_id, "]"));
    }
    torch::NoGradGuard no_grad;
    const torch::Device device = text_model->final_layer_norm->weight.device();
    return forward(ids.to(device), taps);
  });
}

absl::StatusOr<torch::Tensor> ClipTextModelImpl::PromptEmbeds(const torch::Tensor& input_ids,
                                                              int clip_skip) {
  if (clip_skip < 0 || clip_skip >= config_.num_hidden_layers) {
    return absl::InvalidArgumentError(
        absl::StrCat("clip_skip must be in [0, ", config_.num_hidden_layers, "), got ", clip_skip));
  }
  FD_ASSIGN_OR_RETURN(ClipTextOutput out, Run(input_ids));
  if (clip_skip == 0) return out.last_hidden_state;
  return TorchCall("ClipTextModel::PromptEmbeds", [&]() -> absl::StatusOr<torch::Tensor> {
    torch::NoGradGuard no_grad;
    const auto& hs = out.hidden_states;
    return text_model->final_layer_norm(hs[hs.size() - 1 - clip_skip]);
  });
}

absl::StatusOr<ClipTextModel> MakeClipTextModel(const CLIPTextConfig& config) {
  if (config.hidden_size < 1 || config.num_attention_heads < 1 ||
      config.hidden_size % config.num_attention_heads != 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        "text encoder config: hidden_size (", config.hidden_size,
        ") must be a positive multiple of num_attention_heads (", config.num_attention_heads, ")"));
  }
  if (config.vocab_size < 1 || config.intermediate_size < 1 || config.num_hidden_layers < 1 ||
      config.max_position_embeddings < 1) {
    return absl::InvalidArgumentError(
        "text encoder config: vocab_size, intermediate_size, num_hidden_layers and "
        "max_position_embeddings must be positive");
  }
  if (config.hidden_act != "quick_gelu" && config.hidden_act != "gelu") {
    return absl::UnimplementedError(absl::StrCat("text encoder config: hidden_act '",
                                                 config.hidden_act,
                                                 "' (only quick_gelu and gelu are supported)"));
  }
  return TorchCall("MakeClipTextModel", [&]() -> absl::StatusOr<ClipTextModel> {
    ClipTextModel model(config);
    torch::NoGradGuard no_grad;
    for (auto& p : model->parameters()) p.zero_();
    model->eval();
    return model;
  });
}

absl::StatusOr<ClipTextModel> LoadClipTextModel(const std::string& dir, torch::Device device,
                                                torch::Dtype dtype, const FileSource& files) {
  FD_ASSIGN_OR_RETURN(const CLIPTextConfig config, LoadCLIPTextConfig(dir + "/config.json", files));
  FD_ASSIGN_OR_RETURN(ClipTextModel model, MakeClipTextModel(config));
  FD_ASSIGN_OR_RETURN(std::unique_ptr<SafetensorsFile> file,
                      files.OpenSafetensors(dir + "/model.safetensors"));
  LoadOptions options;
  // transformers >= 4.31 no longer saves the position_ids buffer.
  options.allow_missing = [](const std::string& name) {
    return name == "text_model.embeddings.position_ids";
  };
  FD_RETURN_IF_ERROR(LoadStateDict(*model, *file, options));
  FD_RETURN_IF_ERROR(MoveModule(*model, device, dtype));
  return model;
}

absl::StatusOr<torch::Tensor> EncodePrompts(const ClipTokenizer& tokenizer, ClipTextModel& model,
                                            const std::vector<std::string>& prompts,
                                            int clip_skip) {
  if (prompts.empty()) return absl::InvalidArgumentError("prompts: at least one prompt needed");
  FD_ASSIGN_OR_RETURN(
      torch::Tensor ids,
      tokenizer.EncodeBatch(prompts, static_cast<int>(model->config().max_position_embeddings)));
  return model->PromptEmbeds(ids, clip_skip);
}

absl::StatusOr<torch::Tensor> LoadPromptEmbeds(const std::string& path, const FileSource& files) {
  FD_ASSIGN_OR_RETURN(std::unique_ptr<SafetensorsFile> file, files.OpenSafetensors(path));
  const std::vector<std::string> keys = file->Keys();
  std::string key = "prompt_embeds";
  if (!file->Contains(key)) {
    if (keys.size() != 1) {
      return absl::InvalidArgumentError(
          absl::StrCat(path, ": no tensor 'prompt_embeds' (and not a single-tensor file); has ",
                       absl::StrJoin(keys, ", ")));
    }
    key = keys[0];
  }
  FD_ASSIGN_OR_RETURN(torch::Tensor embeds, file->Get(key));
  return TorchCall("LoadPromptEmbeds", [&]() -> absl::StatusOr<torch::Tensor> {
    if (!embeds.is_floating_point() || (embeds.dim() != 2 && embeds.dim() != 3) ||
        embeds.numel() == 0) {
      return absl::InvalidArgumentError(absl::StrCat(
          path, ": '", key, "' must be a floating-point [N, L, H] or [L, H] tensor, got ",
          std::string(c10::toString(embeds.scalar_type())), " [",
          absl::StrJoin(embeds.sizes(), ", "), "]"));
    }
    if (!torch::isfinite(embeds).all().item<bool>()) {
      return absl::InvalidArgumentError(absl::StrCat(path, ": '", key, "' contains NaN or Inf"));
    }
    return embeds.dim() == 2 ? embeds.unsqueeze(0) : embeds;
  });
}

}  // namespace fd::model

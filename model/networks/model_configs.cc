// config.json parsing; see model_configs.h. Defaults and checks follow the
// __init__ of diffusers v0.31.0 UNet2DConditionModel, ControlNetModel,
// AutoencoderKL and transformers 4.30 CLIPTextConfig.
#include "model/networks/model_configs.h"

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <fstream>
#include <limits>
#include <nlohmann/json.hpp>
#include <set>
#include <sstream>
#include <type_traits>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "base/status_macros.h"
#include "model/checkpoint/json_non_finite.h"

namespace fd::model {
namespace {

using Json = nlohmann::json;

// The JSON value as text for messages (markers shown as the original token).
std::string Show(const Json& value) {
  if (auto non_finite = NonFiniteFromMarker(value)) {
    return std::isnan(*non_finite) ? "NaN" : (*non_finite > 0 ? "Infinity" : "-Infinity");
  }
  std::string text = value.dump();
  if (text.size() > 200) text = text.substr(0, 200) + "...";
  return text;
}

// Typed access to the keys of one config object. Every reader leaves the
// output untouched when the key is absent (or listed in
// `_use_default_values`) and returns INVALID_ARGUMENT naming the source and
// the key for a value of the wrong type.
class ConfigReader {
 public:
  static absl::StatusOr<ConfigReader> Parse(const std::string& text, const std::string& source) {
    Json json = Json::parse(QuoteNonFiniteJsonTokens(text), /*cb=*/nullptr,
                            /*allow_exceptions=*/false);
    if (json.is_discarded()) {
      return absl::InvalidArgumentError(absl::StrCat("config '", source, "': not valid JSON"));
    }
    if (!json.is_object()) {
      return absl::InvalidArgumentError(
          absl::StrCat("config '", source, "': a JSON ", json.type_name(), ", expected an object"));
    }
    ConfigReader reader(std::move(json), source);
    if (const auto it = reader.json_.find("_use_default_values"); it != reader.json_.end()) {
      if (!it->is_array()) return reader.Error("_use_default_values", "is not a list");
      for (const Json& key : *it) {
        if (!key.is_string()) return reader.Error("_use_default_values", "holds a non-string");
        reader.use_defaults_.insert(key.get<std::string>());
      }
    }
    return reader;
  }

  const std::string& source() const { return source_; }

  absl::Status Error(const std::string& key, const std::string& what) const {
    return absl::InvalidArgumentError(
        absl::StrCat("config '", source_, "': key '", key, "' ", what));
  }
  absl::Status WrongType(const std::string& key, const char* expected) const {
    return Error(key, absl::StrCat("must be ", expected, ", got ", Show(*Find(key))));
  }

  // The value of `key`; null when absent or defaulted.
  const Json* Find(const std::string& key) const {
    if (use_defaults_.count(key) != 0) return nullptr;
    const auto it = json_.find(key);
    return it == json_.end() ? nullptr : &*it;
  }
  // Present with a non-null value.
  bool HasValue(const std::string& key) const {
    const Json* value = Find(key);
    return value != nullptr && !value->is_null();
  }

  absl::Status Read(const std::string& key, int64_t* out) const {
    const Json* value = Find(key);
    if (value == nullptr) return absl::OkStatus();
    if (!value->is_number_integer()) return WrongType(key, "an integer");
    *out = value->get<int64_t>();
    return absl::OkStatus();
  }
  absl::Status Read(const std::string& key, double* out) const {
    const Json* value = Find(key);
    if (value == nullptr) return absl::OkStatus();
    if (auto non_finite = NonFiniteFromMarker(*value)) {
      *out = *non_finite;
      return absl::OkStatus();
    }
    if (!value->is_number()) return WrongType(key, "a number");
    *out = value->get<double>();
    return absl::OkStatus();
  }
  absl::Status Read(const std::string& key, bool* out) const {
    const Json* value = Find(key);
    if (value == nullptr) return absl::OkStatus();
    if (!value->is_boolean()) return WrongType(key, "true or false");
    *out = value->get<bool>();
    return absl::OkStatus();
  }
  absl::Status Read(const std::string& key, std::string* out) const {
    const Json* value = Find(key);
    if (value == nullptr) return absl::OkStatus();
    if (!value->is_string() || NonFiniteFromMarker(*value)) return WrongType(key, "a string");
    *out = value->get<std::string>();
    return absl::OkStatus();
  }
  // null -> nullopt.
  template <typename T>
  absl::Status Read(const std::string& key, std::optional<T>* out) const {
    const Json* value = Find(key);
    if (value == nullptr) return absl::OkStatus();
    if (value->is_null()) {
      out->reset();
      return absl::OkStatus();
    }
    T parsed{};
    FD_RETURN_IF_ERROR(Read(key, &parsed));
    *out = std::move(parsed);
    return absl::OkStatus();
  }
  absl::Status Read(const std::string& key, std::vector<int64_t>* out) const {
    const Json* value = Find(key);
    if (value == nullptr) return absl::OkStatus();
    if (!value->is_array()) return WrongType(key, "a list of integers");
    std::vector<int64_t> parsed;
    for (const Json& item : *value) {
      if (!item.is_number_integer()) return WrongType(key, "a list of integers");
      parsed.push_back(item.get<int64_t>());
    }
    *out = std::move(parsed);
    return absl::OkStatus();
  }
  absl::Status Read(const std::string& key, std::vector<double>* out) const {
    const Json* value = Find(key);
    if (value == nullptr) return absl::OkStatus();
    if (!value->is_array()) return WrongType(key, "a list of numbers");
    std::vector<double> parsed;
    for (const Json& item : *value) {
      if (auto non_finite = NonFiniteFromMarker(item)) {
        parsed.push_back(*non_finite);
        continue;
      }
      if (!item.is_number()) return WrongType(key, "a list of numbers");
      parsed.push_back(item.get<double>());
    }
    *out = std::move(parsed);
    return absl::OkStatus();
  }
  absl::Status Read(const std::string& key, std::vector<std::string>* out) const {
    const Json* value = Find(key);
    if (value == nullptr) return absl::OkStatus();
    if (!value->is_array()) return WrongType(key, "a list of strings");
    std::vector<std::string> parsed;
    for (const Json& item : *value) {
      if (!item.is_string()) return WrongType(key, "a list of strings");
      parsed.push_back(item.get<std::string>());
    }
    *out = std::move(parsed);
    return absl::OkStatus();
  }

  // diffusers' "int or tuple" arguments: one value for every down block or a
  // list with one entry per block. Absent: `num_blocks` copies of
  // `default_value`.
  template <typename T>
  absl::Status ReadPerBlock(const std::string& key, size_t num_blocks, T default_value,
                            std::vector<T>* out) const {
    const Json* value = Find(key);
    if (value == nullptr) {
      out->assign(num_blocks, default_value);
      return absl::OkStatus();
    }
    auto read_one = [&](const Json& item, T* result) -> bool {
      if constexpr (std::is_same_v<T, bool>) {
        if (!item.is_boolean()) return false;
        *result = item.get<bool>();
      } else {
        if (!item.is_number_integer()) return false;
        *result = item.get<int64_t>();
      }
      return true;
    };
    const char* expected = std::is_same_v<T, bool> ? "a boolean or a list of booleans"
                                                   : "an integer or a list of integers";
    if (value->is_array()) {
      if (value->size() != num_blocks) {
        return Error(key, absl::StrCat("has ", value->size(), " entries but there are ", num_blocks,
                                       " down blocks"));
      }
      std::vector<T> parsed;
      for (const Json& item : *value) {
        T one{};
        if (item.is_array()) {
          return Error(key,
                       "holds nested lists (per-layer values, as SDXL refiner configs use), "
                       "which are not supported");
        }
        if (!read_one(item, &one)) return WrongType(key, expected);
        parsed.push_back(one);
      }
      *out = std::move(parsed);
      return absl::OkStatus();
    }
    T one{};
    if (!read_one(*value, &one)) return WrongType(key, expected);
    out->assign(num_blocks, one);
    return absl::OkStatus();
  }

  // The key must be absent, null or `allowed` (a diffusers option with a
  // non-default value this port does not implement): UNIMPLEMENTED otherwise.
  absl::Status RequireDefault(const std::string& key, const Json& allowed = nullptr) const {
    const Json* value = Find(key);
    if (value == nullptr || value->is_null() || *value == allowed) return absl::OkStatus();
    return absl::UnimplementedError(absl::StrCat(
        "config '", source_, "': key '", key, "' = ", Show(*value),
        " is not supported by this port (supported: ", allowed.is_null() ? "null" : allowed.dump(),
        ")"));
  }

 private:
  ConfigReader(Json json, std::string source)
      : json_(std::move(json)), source_(std::move(source)) {}

  Json json_;
  std::string source_;
  std::set<std::string> use_defaults_;
};

absl::Status RequirePositive(const ConfigReader& reader, const std::string& key, int64_t value) {
  if (value <= 0) return reader.Error(key, absl::StrCat("must be positive, got ", value));
  return absl::OkStatus();
}

absl::Status RequirePositive(const ConfigReader& reader, const std::string& key,
                             const std::vector<int64_t>& values) {
  for (int64_t value : values) {
    if (value <= 0) {
      return reader.Error(
          key, absl::StrCat("must hold positive values, got [", absl::StrJoin(values, ", "), "]"));
    }
  }
  return absl::OkStatus();
}

absl::Status RequireOneOf(const ConfigReader& reader, const std::string& key,
                          const std::string& value, const std::vector<std::string>& allowed,
                          absl::StatusCode code = absl::StatusCode::kInvalidArgument) {
  if (std::find(allowed.begin(), allowed.end(), value) != allowed.end()) {
    return absl::OkStatus();
  }
  return absl::Status(
      code, absl::StrCat("config '", reader.source(), "': key '", key, "' = '", value,
                         "' is not supported (supported: ", absl::StrJoin(allowed, ", "), ")"));
}

absl::Status RequireClassName(const ConfigReader& reader, const std::string& class_name,
                              const std::vector<std::string>& allowed) {
  if (class_name.empty()) return absl::OkStatus();
  if (std::find(allowed.begin(), allowed.end(), class_name) != allowed.end()) {
    return absl::OkStatus();
  }
  return reader.Error("_class_name", absl::StrCat("is '", class_name, "', expected one of ",
                                                  absl::StrJoin(allowed, ", ")));
}

const std::vector<std::string>& SupportedDownBlockTypes() {
  static const auto* types = new std::vector<std::string>{"CrossAttnDownBlock2D", "DownBlock2D"};
  return *types;
}
const std::vector<std::string>& SupportedUpBlockTypes() {
  static const auto* types = new std::vector<std::string>{"CrossAttnUpBlock2D", "UpBlock2D"};
  return *types;
}

absl::Status CheckBlockTypes(const ConfigReader& reader, const std::string& key,
                             const std::vector<std::string>& types,
                             const std::vector<std::string>& supported) {
  for (const std::string& type : types) {
    if (std::find(supported.begin(), supported.end(), type) == supported.end()) {
      return reader.Error(key,
                          absl::StrCat("contains the unknown or unsupported block type '", type,
                                       "' (supported: ", absl::StrJoin(supported, ", "), ")"));
    }
  }
  return absl::OkStatus();
}

// The fields UNet2DConditionModel and ControlNetModel share.
absl::Status ReadUNetCommon(const ConfigReader& reader, bool allow_per_block_layers,
                            UNetCommonConfig* config) {
  FD_RETURN_IF_ERROR(reader.Read("_class_name", &config->class_name));
  FD_RETURN_IF_ERROR(reader.Read("in_channels", &config->in_channels));
  FD_RETURN_IF_ERROR(RequirePositive(reader, "in_channels", config->in_channels));
  FD_RETURN_IF_ERROR(reader.Read("flip_sin_to_cos", &config->flip_sin_to_cos));
  FD_RETURN_IF_ERROR(reader.Read("freq_shift", &config->freq_shift));
  FD_RETURN_IF_ERROR(reader.Read("down_block_types", &config->down_block_types));
  if (config->down_block_types.empty()) return reader.Error("down_block_types", "is empty");
  FD_RETURN_IF_ERROR(CheckBlockTypes(reader, "down_block_types", config->down_block_types,
                                     SupportedDownBlockTypes()));
  FD_RETURN_IF_ERROR(reader.Read("mid_block_type", &config->mid_block_type));
  if (reader.Find("mid_block_type") != nullptr && reader.Find("mid_block_type")->is_null()) {
    return absl::UnimplementedError(
        absl::StrCat("config '", reader.source(),
                     "': key 'mid_block_type' = null (no mid block) is not supported"));
  }
  FD_RETURN_IF_ERROR(
      RequireOneOf(reader, "mid_block_type", config->mid_block_type, {"UNetMidBlock2DCrossAttn"}));

  const size_t num_blocks = config->down_block_types.size();
  FD_RETURN_IF_ERROR(reader.Read("block_out_channels", &config->block_out_channels));
  if (config->block_out_channels.size() != num_blocks) {
    return reader.Error("block_out_channels",
                        absl::StrCat("has ", config->block_out_channels.size(),
                                     " entries but down_block_types has ", num_blocks));
  }
  FD_RETURN_IF_ERROR(RequirePositive(reader, "block_out_channels", config->block_out_channels));

  if (allow_per_block_layers) {
    FD_RETURN_IF_ERROR(
        reader.ReadPerBlock<int64_t>("layers_per_block", num_blocks, 2, &config->layers_per_block));
  } else {
    int64_t layers = 2;
    FD_RETURN_IF_ERROR(reader.Read("layers_per_block", &layers));
    config->layers_per_block.assign(num_blocks, layers);
  }
  FD_RETURN_IF_ERROR(RequirePositive(reader, "layers_per_block", config->layers_per_block));
  FD_RETURN_IF_ERROR(reader.ReadPerBlock<bool>("only_cross_attention", num_blocks, false,
                                               &config->only_cross_attention));
  if (std::find(config->only_cross_attention.begin(), config->only_cross_attention.end(), true) !=
      config->only_cross_attention.end()) {
    return absl::UnimplementedError(absl::StrCat("config '", reader.source(),
                                                 "': key 'only_cross_attention' = true is not "
                                                 "supported by this port"));
  }
  FD_RETURN_IF_ERROR(reader.ReadPerBlock<int64_t>("cross_attention_dim", num_blocks, 1280,
                                                  &config->cross_attention_dim));
  FD_RETURN_IF_ERROR(RequirePositive(reader, "cross_attention_dim", config->cross_attention_dim));
  FD_RETURN_IF_ERROR(reader.ReadPerBlock<int64_t>("transformer_layers_per_block", num_blocks, 1,
                                                  &config->transformer_layers_per_block));
  FD_RETURN_IF_ERROR(RequirePositive(reader, "transformer_layers_per_block",
                                     config->transformer_layers_per_block));
  if (reader.Find("attention_head_dim") != nullptr &&
      reader.Find("attention_head_dim")->is_null()) {
    return reader.Error("attention_head_dim", "must not be null");
  }
  FD_RETURN_IF_ERROR(reader.ReadPerBlock<int64_t>("attention_head_dim", num_blocks, 8,
                                                  &config->attention_head_dim));
  FD_RETURN_IF_ERROR(RequirePositive(reader, "attention_head_dim", config->attention_head_dim));
  if (reader.HasValue("num_attention_heads")) {
    std::vector<int64_t> heads;
    FD_RETURN_IF_ERROR(reader.ReadPerBlock<int64_t>("num_attention_heads", num_blocks, 0, &heads));
    FD_RETURN_IF_ERROR(RequirePositive(reader, "num_attention_heads", heads));
    config->num_attention_heads = std::move(heads);
  } else {
    config->num_attention_heads.reset();
  }
  FD_RETURN_IF_ERROR(reader.Read("downsample_padding", &config->downsample_padding));
  FD_RETURN_IF_ERROR(reader.Read("mid_block_scale_factor", &config->mid_block_scale_factor));
  FD_RETURN_IF_ERROR(reader.Read("act_fn", &config->act_fn));
  FD_RETURN_IF_ERROR(
      RequireOneOf(reader, "act_fn", config->act_fn, {"silu"}, absl::StatusCode::kUnimplemented));
  if (reader.Find("norm_num_groups") != nullptr && reader.Find("norm_num_groups")->is_null()) {
    return absl::UnimplementedError(absl::StrCat(
        "config '", reader.source(), "': key 'norm_num_groups' = null is not supported"));
  }
  FD_RETURN_IF_ERROR(reader.Read("norm_num_groups", &config->norm_num_groups));
  FD_RETURN_IF_ERROR(RequirePositive(reader, "norm_num_groups", config->norm_num_groups));
  FD_RETURN_IF_ERROR(reader.Read("norm_eps", &config->norm_eps));
  FD_RETURN_IF_ERROR(reader.Read("use_linear_projection", &config->use_linear_projection));
  FD_RETURN_IF_ERROR(reader.Read("upcast_attention", &config->upcast_attention));
  FD_RETURN_IF_ERROR(reader.Read("resnet_time_scale_shift", &config->resnet_time_scale_shift));
  FD_RETURN_IF_ERROR(RequireOneOf(reader, "resnet_time_scale_shift",
                                  config->resnet_time_scale_shift, {"default"},
                                  absl::StatusCode::kUnimplemented));

  // Conditioning inputs beyond timestep + text that SD1.5 does not use.
  for (const char* key : {"class_embed_type", "addition_embed_type", "num_class_embeds",
                          "encoder_hid_dim", "encoder_hid_dim_type"}) {
    FD_RETURN_IF_ERROR(reader.RequireDefault(key));
  }
  return absl::OkStatus();
}

absl::StatusOr<UNet2DConditionConfig> ParseUNet(const ConfigReader& reader) {
  UNet2DConditionConfig config;
  FD_RETURN_IF_ERROR(ReadUNetCommon(reader, /*allow_per_block_layers=*/true, &config));
  FD_RETURN_IF_ERROR(RequireClassName(reader, config.class_name,
                                      {"UNet2DConditionModel", "UNet2DConditionModelEx"}));
  if (config.num_attention_heads.has_value()) {
    // diffusers' UNet2DConditionModel.__init__ raises here (issue #2011): its
    // attention_head_dim already means the number of heads.
    return reader.Error("num_attention_heads",
                        "must be null for UNet2DConditionModel (diffusers raises: "
                        "attention_head_dim holds the number of heads, see diffusers issue #2011)");
  }
  const size_t num_blocks = config.down_block_types.size();
  FD_RETURN_IF_ERROR(reader.Read("sample_size", &config.sample_size));
  FD_RETURN_IF_ERROR(reader.Read("out_channels", &config.out_channels));
  FD_RETURN_IF_ERROR(RequirePositive(reader, "out_channels", config.out_channels));
  FD_RETURN_IF_ERROR(reader.Read("up_block_types", &config.up_block_types));
  if (config.up_block_types.size() != num_blocks) {
    return reader.Error("up_block_types",
                        absl::StrCat("has ", config.up_block_types.size(),
                                     " entries but down_block_types has ", num_blocks));
  }
  FD_RETURN_IF_ERROR(
      CheckBlockTypes(reader, "up_block_types", config.up_block_types, SupportedUpBlockTypes()));
  FD_RETURN_IF_ERROR(reader.Read("reverse_transformer_layers_per_block",
                                 &config.reverse_transformer_layers_per_block));
  if (config.reverse_transformer_layers_per_block &&
      config.reverse_transformer_layers_per_block->size() != num_blocks) {
    return reader.Error("reverse_transformer_layers_per_block",
                        absl::StrCat("has ", config.reverse_transformer_layers_per_block->size(),
                                     " entries but there are ", num_blocks, " up blocks"));
  }
  FD_RETURN_IF_ERROR(reader.Read("dropout", &config.dropout));
  FD_RETURN_IF_ERROR(reader.Read("conv_in_kernel", &config.conv_in_kernel));
  FD_RETURN_IF_ERROR(reader.Read("conv_out_kernel", &config.conv_out_kernel));
  for (const auto& [key, kernel] : {std::pair{"conv_in_kernel", config.conv_in_kernel},
                                    std::pair{"conv_out_kernel", config.conv_out_kernel}}) {
    if (kernel <= 0 || kernel % 2 == 0) {
      return reader.Error(key, absl::StrCat("must be a positive odd number, got ", kernel));
    }
  }
  FD_RETURN_IF_ERROR(reader.Read("time_embedding_dim", &config.time_embedding_dim));
  if (config.time_embedding_dim) {
    FD_RETURN_IF_ERROR(RequirePositive(reader, "time_embedding_dim", *config.time_embedding_dim));
  }
  FD_RETURN_IF_ERROR(reader.Read("resnet_out_scale_factor", &config.resnet_out_scale_factor));
  FD_RETURN_IF_ERROR(reader.Read("extra_condition_names", &config.extra_condition_names));
  FD_RETURN_IF_ERROR(reader.Read("basecolor_patch_channels", &config.basecolor_patch_channels));
  if (config.basecolor_patch_channels < 0 || config.basecolor_patch_channels % 3 != 0) {
    return reader.Error("basecolor_patch_channels",
                        absl::StrCat("must be 0 or 3 * f * f (f: the VAE's downsampling), got ",
                                     config.basecolor_patch_channels));
  }

  // diffusers options whose non-default values change the network; the port
  // implements the SD1.5 path only.
  FD_RETURN_IF_ERROR(reader.RequireDefault("center_input_sample", false));
  FD_RETURN_IF_ERROR(reader.RequireDefault("time_embedding_type", "positional"));
  FD_RETURN_IF_ERROR(reader.RequireDefault("attention_type", "default"));
  FD_RETURN_IF_ERROR(reader.RequireDefault("dual_cross_attention", false));
  FD_RETURN_IF_ERROR(reader.RequireDefault("resnet_skip_time_act", false));
  for (const char* key : {"time_embedding_act_fn", "timestep_post_act", "time_cond_proj_dim",
                          "cross_attention_norm"}) {
    FD_RETURN_IF_ERROR(reader.RequireDefault(key));
  }
  return config;
}

absl::StatusOr<ControlNetConfig> ParseControlNet(const ConfigReader& reader) {
  ControlNetConfig config;
  FD_RETURN_IF_ERROR(ReadUNetCommon(reader, /*allow_per_block_layers=*/false, &config));
  FD_RETURN_IF_ERROR(
      RequireClassName(reader, config.class_name, {"ControlNetModel", "ControlNetModelEx"}));
  FD_RETURN_IF_ERROR(reader.Read("conditioning_channels", &config.conditioning_channels));
  FD_RETURN_IF_ERROR(
      RequirePositive(reader, "conditioning_channels", config.conditioning_channels));
  FD_RETURN_IF_ERROR(reader.Read("controlnet_conditioning_channel_order",
                                 &config.controlnet_conditioning_channel_order));
  FD_RETURN_IF_ERROR(RequireOneOf(reader, "controlnet_conditioning_channel_order",
                                  config.controlnet_conditioning_channel_order, {"rgb", "bgr"}));
  const bool is_ex = config.class_name == "ControlNetModelEx";
  if (is_ex) config.conditioning_embedding_out_channels = {64, 96, 256, 512};
  FD_RETURN_IF_ERROR(reader.Read("conditioning_embedding_out_channels",
                                 &config.conditioning_embedding_out_channels));
  if (config.conditioning_embedding_out_channels.empty()) {
    return reader.Error("conditioning_embedding_out_channels", "is empty");
  }
  if (is_ex && config.conditioning_embedding_out_channels.size() != 4) {
    return reader.Error("conditioning_embedding_out_channels",
                        absl::StrCat("must have 4 entries for ControlNetModelEx (9-conv encoder), "
                                     "got ",
                                     config.conditioning_embedding_out_channels.size()));
  }
  FD_RETURN_IF_ERROR(RequirePositive(reader, "conditioning_embedding_out_channels",
                                     config.conditioning_embedding_out_channels));
  FD_RETURN_IF_ERROR(reader.Read("global_pool_conditions", &config.global_pool_conditions));
  FD_RETURN_IF_ERROR(reader.Read("gbuffer_channels", &config.gbuffer_channels));
  if (config.gbuffer_channels) {
    FD_RETURN_IF_ERROR(RequirePositive(reader, "gbuffer_channels", *config.gbuffer_channels));
  }
  return config;
}

absl::StatusOr<AutoencoderKLConfig> ParseVae(const ConfigReader& reader) {
  AutoencoderKLConfig config;
  FD_RETURN_IF_ERROR(reader.Read("_class_name", &config.class_name));
  FD_RETURN_IF_ERROR(RequireClassName(reader, config.class_name, {"AutoencoderKL"}));
  FD_RETURN_IF_ERROR(reader.Read("in_channels", &config.in_channels));
  FD_RETURN_IF_ERROR(RequirePositive(reader, "in_channels", config.in_channels));
  FD_RETURN_IF_ERROR(reader.Read("out_channels", &config.out_channels));
  FD_RETURN_IF_ERROR(RequirePositive(reader, "out_channels", config.out_channels));
  FD_RETURN_IF_ERROR(reader.Read("down_block_types", &config.down_block_types));
  FD_RETURN_IF_ERROR(reader.Read("up_block_types", &config.up_block_types));
  FD_RETURN_IF_ERROR(reader.Read("block_out_channels", &config.block_out_channels));
  if (config.block_out_channels.empty()) return reader.Error("block_out_channels", "is empty");
  FD_RETURN_IF_ERROR(RequirePositive(reader, "block_out_channels", config.block_out_channels));
  for (const auto& [key, types] : {std::pair{"down_block_types", &config.down_block_types},
                                   std::pair{"up_block_types", &config.up_block_types}}) {
    if (types->size() != config.block_out_channels.size()) {
      return reader.Error(
          key, absl::StrCat("has ", types->size(), " entries but block_out_channels has ",
                            config.block_out_channels.size()));
    }
  }
  FD_RETURN_IF_ERROR(
      CheckBlockTypes(reader, "down_block_types", config.down_block_types, {"DownEncoderBlock2D"}));
  FD_RETURN_IF_ERROR(
      CheckBlockTypes(reader, "up_block_types", config.up_block_types, {"UpDecoderBlock2D"}));
  FD_RETURN_IF_ERROR(reader.Read("layers_per_block", &config.layers_per_block));
  FD_RETURN_IF_ERROR(RequirePositive(reader, "layers_per_block", config.layers_per_block));
  FD_RETURN_IF_ERROR(reader.Read("act_fn", &config.act_fn));
  FD_RETURN_IF_ERROR(
      RequireOneOf(reader, "act_fn", config.act_fn, {"silu"}, absl::StatusCode::kUnimplemented));
  FD_RETURN_IF_ERROR(reader.Read("latent_channels", &config.latent_channels));
  FD_RETURN_IF_ERROR(RequirePositive(reader, "latent_channels", config.latent_channels));
  FD_RETURN_IF_ERROR(reader.Read("norm_num_groups", &config.norm_num_groups));
  FD_RETURN_IF_ERROR(RequirePositive(reader, "norm_num_groups", config.norm_num_groups));
  FD_RETURN_IF_ERROR(reader.Read("sample_size", &config.sample_size));
  FD_RETURN_IF_ERROR(reader.Read("scaling_factor", &config.scaling_factor));
  if (!(config.scaling_factor > 0.0) || !std::isfinite(config.scaling_factor)) {
    return reader.Error("scaling_factor", absl::StrCat("must be a positive finite number, got ",
                                                       config.scaling_factor));
  }
  FD_RETURN_IF_ERROR(reader.Read("shift_factor", &config.shift_factor));
  FD_RETURN_IF_ERROR(reader.Read("latents_mean", &config.latents_mean));
  FD_RETURN_IF_ERROR(reader.Read("latents_std", &config.latents_std));
  FD_RETURN_IF_ERROR(reader.Read("force_upcast", &config.force_upcast));
  FD_RETURN_IF_ERROR(reader.Read("use_quant_conv", &config.use_quant_conv));
  FD_RETURN_IF_ERROR(reader.Read("use_post_quant_conv", &config.use_post_quant_conv));
  FD_RETURN_IF_ERROR(reader.Read("mid_block_add_attention", &config.mid_block_add_attention));
  return config;
}

absl::StatusOr<CLIPTextConfig> ParseClip(const ConfigReader& reader) {
  CLIPTextConfig config;
  for (const auto& [key, field] : std::initializer_list<std::pair<const char*, int64_t*>>{
           {"vocab_size", &config.vocab_size},
           {"hidden_size", &config.hidden_size},
           {"intermediate_size", &config.intermediate_size},
           {"projection_dim", &config.projection_dim},
           {"num_hidden_layers", &config.num_hidden_layers},
           {"num_attention_heads", &config.num_attention_heads},
           {"max_position_embeddings", &config.max_position_embeddings}}) {
    FD_RETURN_IF_ERROR(reader.Read(key, field));
    FD_RETURN_IF_ERROR(RequirePositive(reader, key, *field));
  }
  if (config.hidden_size % config.num_attention_heads != 0) {
    return reader.Error("num_attention_heads",
                        absl::StrCat("= ", config.num_attention_heads,
                                     " does not divide hidden_size ", config.hidden_size));
  }
  FD_RETURN_IF_ERROR(reader.Read("hidden_act", &config.hidden_act));
  FD_RETURN_IF_ERROR(RequireOneOf(reader, "hidden_act", config.hidden_act, {"quick_gelu", "gelu"},
                                  absl::StatusCode::kUnimplemented));
  FD_RETURN_IF_ERROR(reader.Read("layer_norm_eps", &config.layer_norm_eps));
  FD_RETURN_IF_ERROR(reader.Read("attention_dropout", &config.attention_dropout));
  FD_RETURN_IF_ERROR(reader.Read("initializer_range", &config.initializer_range));
  FD_RETURN_IF_ERROR(reader.Read("initializer_factor", &config.initializer_factor));
  FD_RETURN_IF_ERROR(reader.Read("pad_token_id", &config.pad_token_id));
  FD_RETURN_IF_ERROR(reader.Read("bos_token_id", &config.bos_token_id));
  FD_RETURN_IF_ERROR(reader.Read("eos_token_id", &config.eos_token_id));
  return config;
}

template <typename Config>
absl::StatusOr<Config> ParseWith(absl::StatusOr<Config> (*parse)(const ConfigReader&),
                                 const std::string& json_text, const std::string& source) {
  FD_ASSIGN_OR_RETURN(const ConfigReader reader, ConfigReader::Parse(json_text, source));
  return parse(reader);
}

template <typename Config>
absl::StatusOr<Config> LoadWith(absl::StatusOr<Config> (*parse)(const ConfigReader&),
                                const std::string& path, const FileSource& files) {
  FD_ASSIGN_OR_RETURN(const std::string text, files.ReadText(path));
  return ParseWith(parse, text, path);
}

// Heads and head width of a cross-attention block with `channels` channels.
absl::Status SetAttention(const std::string& block_name, int64_t channels, int64_t heads,
                          UNetBlockLayout* block) {
  if (heads <= 0 || channels % heads != 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        block_name, ": ", channels, " channels do not split into ", heads, " attention heads"));
  }
  block->num_attention_heads = heads;
  block->attention_head_dim = channels / heads;
  return absl::OkStatus();
}

// Down and mid blocks, shared by the UNet and the ControlNet (diffusers
// builds both with the same loop).
absl::Status ComputeEncoderLayout(const UNetCommonConfig& config, UNetLayout* layout) {
  const std::vector<int64_t> heads = config.HeadsPerDownBlock();
  const size_t num_blocks = config.down_block_types.size();
  if (config.block_out_channels.size() != num_blocks || heads.size() != num_blocks ||
      config.layers_per_block.size() != num_blocks ||
      config.cross_attention_dim.size() != num_blocks ||
      config.transformer_layers_per_block.size() != num_blocks) {
    return absl::InvalidArgumentError(
        "UNet config: per-block lists do not match down_block_types in length");
  }
  int64_t output_channel = config.block_out_channels[0];
  for (size_t i = 0; i < num_blocks; ++i) {
    UNetBlockLayout block;
    block.type = config.down_block_types[i];
    block.has_cross_attention = block.type == "CrossAttnDownBlock2D";
    block.in_channels = output_channel;
    output_channel = config.block_out_channels[i];
    block.out_channels = output_channel;
    block.num_layers = config.layers_per_block[i];
    block.add_sampler = i + 1 != num_blocks;
    if (block.has_cross_attention) {
      block.transformer_layers = config.transformer_layers_per_block[i];
      block.cross_attention_dim = config.cross_attention_dim[i];
      FD_RETURN_IF_ERROR(
          SetAttention(absl::StrCat("down_blocks.", i), block.out_channels, heads[i], &block));
    }
    layout->down_blocks.push_back(std::move(block));
  }
  UNetBlockLayout& mid = layout->mid_block;
  mid.type = config.mid_block_type;
  mid.has_cross_attention = true;
  mid.in_channels = mid.out_channels = config.block_out_channels.back();
  mid.num_layers = 1;  // UNetMidBlock2DCrossAttn: 1 attention between 2 resnets
  mid.transformer_layers = config.transformer_layers_per_block.back();
  mid.cross_attention_dim = config.cross_attention_dim.back();
  FD_RETURN_IF_ERROR(SetAttention("mid_block", mid.in_channels, heads.back(), &mid));
  return absl::OkStatus();
}

}  // namespace

std::vector<int64_t> UNetCommonConfig::HeadsPerDownBlock() const {
  return num_attention_heads.has_value() ? *num_attention_heads : attention_head_dim;
}

UNet2DConditionConfig::UNet2DConditionConfig() {
  const size_t n = down_block_types.size();
  layers_per_block.assign(n, 2);
  only_cross_attention.assign(n, false);
  cross_attention_dim.assign(n, 1280);
  transformer_layers_per_block.assign(n, 1);
  attention_head_dim.assign(n, 8);
}

int64_t UNet2DConditionConfig::InputChannels() const {
  if (conv_in_channels > 0) return conv_in_channels;
  return in_channels * (1 + static_cast<int64_t>(extra_condition_names.size()));
}

int64_t UNet2DConditionConfig::FrameDiffuserInputChannels() const {
  return 2 * out_channels + basecolor_patch_channels;
}

int64_t UNet2DConditionConfig::TimeEmbedDim() const {
  return time_embedding_dim.value_or(4 * block_out_channels.at(0));
}

ControlNetConfig::ControlNetConfig() {
  const size_t n = down_block_types.size();
  layers_per_block.assign(n, 2);
  only_cross_attention.assign(n, false);
  cross_attention_dim.assign(n, 1280);
  transformer_layers_per_block.assign(n, 1);
  attention_head_dim.assign(n, 8);
}

int64_t ControlNetConfig::ConditionChannels() const {
  return gbuffer_channels.value_or(conditioning_channels);
}

ControlNetEmbeddingKind DetectControlNetEmbedding(const ControlNetConfig& config,
                                                  const std::vector<std::string>& keys) {
  for (const std::string& key : keys) {
    if (key == "controlnet_cond_embedding.0.weight")
      return ControlNetEmbeddingKind::kFrameDiffuserEx;
    if (key == "controlnet_cond_embedding.conv_in.weight") {
      return ControlNetEmbeddingKind::kDiffusers;
    }
  }
  return config.class_name == "ControlNetModelEx" ? ControlNetEmbeddingKind::kFrameDiffuserEx
                                                  : ControlNetEmbeddingKind::kDiffusers;
}

absl::StatusOr<UNet2DConditionConfig> ParseUNet2DConditionConfig(const std::string& json_text,
                                                                 const std::string& source) {
  return ParseWith(&ParseUNet, json_text, source);
}
absl::StatusOr<ControlNetConfig> ParseControlNetConfig(const std::string& json_text,
                                                       const std::string& source) {
  return ParseWith(&ParseControlNet, json_text, source);
}
absl::StatusOr<AutoencoderKLConfig> ParseAutoencoderKLConfig(const std::string& json_text,
                                                             const std::string& source) {
  return ParseWith(&ParseVae, json_text, source);
}
absl::StatusOr<CLIPTextConfig> ParseCLIPTextConfig(const std::string& json_text,
                                                   const std::string& source) {
  return ParseWith(&ParseClip, json_text, source);
}

absl::StatusOr<UNet2DConditionConfig> LoadUNet2DConditionConfig(const std::string& path,
                                                                const FileSource& files) {
  return LoadWith(&ParseUNet, path, files);
}
absl::StatusOr<ControlNetConfig> LoadControlNetConfig(const std::string& path,
                                                      const FileSource& files) {
  return LoadWith(&ParseControlNet, path, files);
}
absl::StatusOr<AutoencoderKLConfig> LoadAutoencoderKLConfig(const std::string& path,
                                                            const FileSource& files) {
  return LoadWith(&ParseVae, path, files);
}
absl::StatusOr<CLIPTextConfig> LoadCLIPTextConfig(const std::string& path,
                                                  const FileSource& files) {
  return LoadWith(&ParseClip, path, files);
}

absl::StatusOr<int64_t> InferConvInChannels(const UNet2DConditionConfig& config,
                                            const std::vector<int64_t>& shape) {
  const auto shape_text = [&] { return absl::StrCat("[", absl::StrJoin(shape, ", "), "]"); };
  if (shape.size() != 4 || shape[0] != config.block_out_channels.at(0) ||
      shape[2] != config.conv_in_kernel || shape[3] != config.conv_in_kernel) {
    return absl::InvalidArgumentError(absl::StrCat(
        "conv_in.weight has shape ", shape_text(), ", expected [", config.block_out_channels[0],
        ", C, ", config.conv_in_kernel, ", ", config.conv_in_kernel, "]"));
  }
  if (shape[1] < config.in_channels || shape[1] % config.in_channels != 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        "conv_in.weight has shape ", shape_text(), ": its ", shape[1],
        " input channels are not a multiple of the config's in_channels ", config.in_channels));
  }
  return shape[1];
}

absl::StatusOr<UNetLayout> ComputeUNetLayout(const UNet2DConditionConfig& config) {
  UNetLayout layout;
  layout.time_embed_dim = config.TimeEmbedDim();
  FD_RETURN_IF_ERROR(ComputeEncoderLayout(config, &layout));

  const size_t num_blocks = config.up_block_types.size();
  if (num_blocks != config.down_block_types.size()) {
    return absl::InvalidArgumentError(
        "UNet config: up_block_types and down_block_types differ "
        "in length");
  }
  // diffusers reverses every per-block list for the up path.
  auto reversed = [](std::vector<int64_t> values) {
    std::reverse(values.begin(), values.end());
    return values;
  };
  const std::vector<int64_t> channels = reversed(config.block_out_channels);
  const std::vector<int64_t> heads = reversed(config.HeadsPerDownBlock());
  const std::vector<int64_t> layers = reversed(config.layers_per_block);
  const std::vector<int64_t> cross_dims = reversed(config.cross_attention_dim);
  const std::vector<int64_t> transformer_layers =
      config.reverse_transformer_layers_per_block.value_or(
          reversed(config.transformer_layers_per_block));
  if (transformer_layers.size() != num_blocks) {
    return absl::InvalidArgumentError(
        "UNet config: reverse_transformer_layers_per_block does not match up_block_types");
  }
  int64_t output_channel = channels[0];
  for (size_t i = 0; i < num_blocks; ++i) {
    UNetBlockLayout block;
    block.type = config.up_block_types[i];
    block.has_cross_attention = block.type == "CrossAttnUpBlock2D";
    block.prev_output_channel = output_channel;
    output_channel = channels[i];
    block.out_channels = output_channel;
    block.in_channels = channels[std::min(i + 1, num_blocks - 1)];
    block.num_layers = layers[i] + 1;
    block.add_sampler = i + 1 != num_blocks;
    if (block.has_cross_attention) {
      block.transformer_layers = transformer_layers[i];
      block.cross_attention_dim = cross_dims[i];
      FD_RETURN_IF_ERROR(
          SetAttention(absl::StrCat("up_blocks.", i), block.out_channels, heads[i], &block));
    }
    layout.up_blocks.push_back(std::move(block));
  }
  return layout;
}

absl::StatusOr<UNetLayout> ComputeControlNetLayout(const ControlNetConfig& config) {
  UNetLayout layout;
  layout.time_embed_dim = 4 * config.block_out_channels.at(0);
  FD_RETURN_IF_ERROR(ComputeEncoderLayout(config, &layout));
  return layout;
}

}  // namespace fd::model

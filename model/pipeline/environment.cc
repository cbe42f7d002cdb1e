#include "model/pipeline/environment.h"

#include <torch/torch.h>

#include <filesystem>
#include <fstream>
#include <sstream>
#include <utility>

#include "absl/status/status.h"
#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "base/status_macros.h"
#include "model/lora/lora_file.h"
#include "model/runtime/torch_call.h"
#include "model/text/clip_text_model.h"
#include "model/text/clip_tokenizer.h"
#include "nlohmann/json.hpp"

namespace fd::model {
namespace {

namespace fs = std::filesystem;
using json = nlohmann::json;

bool Exists(const FileSource& files, const std::string& path) {
  return files.IsFile(path) || files.IsDirectory(path);
}

// The files of an environment: on disk unless the options name a source.
const FileSource& FilesOf(const EnvironmentOptions& options) {
  return options.files != nullptr ? *options.files : DiskFiles();
}

absl::Status FieldError(absl::string_view source, absl::string_view field, absl::string_view what) {
  return absl::InvalidArgumentError(absl::StrCat(source, ": field '", field, "' ", what));
}

absl::StatusOr<SkyFillMode> SkyModeFromName(absl::string_view name) {
  const std::string lower = absl::AsciiStrToLower(std::string(name));
  if (lower == "sky_image" || lower == "injection") return SkyFillMode::kSkyImage;
  if (lower == "previous_output") return SkyFillMode::kPreviousOutput;
  if (lower == "none") return SkyFillMode::kNone;
  return absl::InvalidArgumentError(
      absl::StrCat("unknown sky mode '", name, "' (expected sky_image, previous_output, none)"));
}

// Reads an optional number field into `out`.
absl::Status ReadNumber(const json& j, absl::string_view source, const char* key, double* out) {
  if (!j.contains(key)) return absl::OkStatus();
  if (!j[key].is_number()) return FieldError(source, key, "must be a number");
  *out = j[key].get<double>();
  return absl::OkStatus();
}

absl::Status ReadInt(const json& j, absl::string_view source, const char* key, int* out) {
  if (!j.contains(key)) return absl::OkStatus();
  if (!j[key].is_number_integer()) return FieldError(source, key, "must be an integer");
  *out = j[key].get<int>();
  return absl::OkStatus();
}

absl::Status ReadString(const json& j, absl::string_view source, const char* key,
                        std::string* out) {
  if (!j.contains(key)) return absl::OkStatus();
  if (!j[key].is_string()) return FieldError(source, key, "must be a string");
  *out = j[key].get<std::string>();
  return absl::OkStatus();
}

// The parts of an environment, wherever they come from.
struct EnvironmentSources {
  std::string dir;             // for messages
  std::string base_dir;        // unet/ vae/ scheduler/ text parts
  std::string controlnet_dir;  // controlnet/
  std::string lora_path;       // empty: search candidates in `dir`
  EnvironmentSettings settings;
};

absl::StatusOr<std::string> FindLora(const FileSource& files, const std::string& dir) {
  for (const char* candidate : kLoraFileCandidates) {
    const std::string path = (fs::path(dir) / candidate).string();
    if (Exists(files, path)) return path;
  }
  return absl::NotFoundError(absl::StrCat("no ControlLoRA file in ", dir, " (looked for ",
                                          absl::StrJoin(kLoraFileCandidates, ", "), ")"));
}

absl::Status LoadText(const EnvironmentSources& sources, const EnvironmentOptions& options,
                      Environment& env) {
  const FileSource& files = FilesOf(options);
  const fs::path base(sources.base_dir);
  const std::string embeds_path = (base / "prompt_embeds.safetensors").string();
  const std::string negative_path = (base / "negative_prompt_embeds.safetensors").string();
  const std::string encoder_dir = (base / "text_encoder").string();
  const std::string tokenizer_dir = (base / "tokenizer").string();
  const int64_t cross_dim = env.unet->config().cross_attention_dim[0];
  auto check_width = [&](const torch::Tensor& t, const std::string& what) -> absl::Status {
    if (t.dim() != 3 || t.size(0) != 1 || t.size(2) != cross_dim) {
      return absl::InvalidArgumentError(
          absl::StrCat(what, ": prompt embeddings must be [1, T, ", cross_dim,
                       "] (the UNet's cross_attention_dim), got ", t.dim(), "-d [",
                       absl::StrJoin(t.sizes(), ", "), "]"));
    }
    return absl::OkStatus();
  };
  if (Exists(files, embeds_path)) {
    FD_ASSIGN_OR_RETURN(torch::Tensor embeds, LoadPromptEmbeds(embeds_path, files));
    FD_RETURN_IF_ERROR(check_width(embeds, embeds_path));
    env.prompt_embeds = embeds.to(env.device, torch::kFloat32);
    if (Exists(files, negative_path)) {
      FD_ASSIGN_OR_RETURN(torch::Tensor negative, LoadPromptEmbeds(negative_path, files));
      FD_RETURN_IF_ERROR(check_width(negative, negative_path));
      env.negative_prompt_embeds = negative.to(env.device, torch::kFloat32);
    }
    return absl::OkStatus();
  }
  if (Exists(files, encoder_dir) || Exists(files, tokenizer_dir)) {
    FD_ASSIGN_OR_RETURN(ClipTokenizer tokenizer,
                        ClipTokenizer::FromDirectory(tokenizer_dir, files));
    FD_ASSIGN_OR_RETURN(ClipTextModel encoder,
                        LoadClipTextModel(encoder_dir, env.device, env.dtype, files));
    // Prompt and negative prompt once per environment (encode_prompt; with
    // CFG the negative prompt "" is what diffusers encodes when none given).
    FD_ASSIGN_OR_RETURN(torch::Tensor embeds,
                        EncodePrompts(tokenizer, encoder,
                                      {sources.settings.prompt, sources.settings.negative_prompt}));
    FD_RETURN_IF_ERROR(TorchCall("encode prompt", [&]() -> absl::Status {
      env.prompt_embeds = embeds.slice(0, 0, 1).to(torch::kFloat32).contiguous();
      env.negative_prompt_embeds = embeds.slice(0, 1, 2).to(torch::kFloat32).contiguous();
      return absl::OkStatus();
    }));
    return check_width(env.prompt_embeds, encoder_dir);
  }
  if (options.allow_missing_text) return absl::OkStatus();
  return absl::NotFoundError(absl::StrCat("no text source in ", sources.base_dir, ": neither ",
                                          embeds_path, " nor ", encoder_dir, " + ", tokenizer_dir));
}

absl::StatusOr<std::shared_ptr<Environment>> LoadFromSources(const EnvironmentSources& sources,
                                                             const EnvironmentOptions& options) {
  auto env = std::make_shared<Environment>();
  env->dir = sources.dir;
  env->settings = sources.settings;
  env->device = options.device;
  env->dtype = options.dtype;
  env->lora_mode = options.lora_mode;
  const FileSource& files = FilesOf(options);
  const fs::path base(sources.base_dir);
  for (const char* part : {"unet", "vae", "scheduler"}) {
    if (!Exists(files, (base / part).string())) {
      return absl::NotFoundError(absl::StrCat("missing folder ", (base / part).string()));
    }
  }
  if (!Exists(files, sources.controlnet_dir)) {
    return absl::NotFoundError(absl::StrCat("missing folder ", sources.controlnet_dir));
  }
  FD_ASSIGN_OR_RETURN(env->unet, LoadUNet((base / "unet").string(), options.device, options.dtype,
                                          /*frame_diffuser_input=*/true, files));
  FD_ASSIGN_OR_RETURN(env->controlnet,
                      LoadControlNet(sources.controlnet_dir, options.device, options.dtype, files));
  FD_ASSIGN_OR_RETURN(env->vae,
                      LoadVae((base / "vae").string(), options.device, options.dtype, files));
  if (const int64_t patches = env->unet->config().basecolor_patch_channels; patches > 0) {
    const int64_t f = env->vae->downsampling_factor();
    if (patches != 3 * f * f) {
      return absl::InvalidArgumentError(
          absl::StrCat((base / "unet" / "config.json").string(), ": basecolor_patch_channels is ",
                       patches, "; the VAE downsamples ", f, "x, so the basecolor patches have ",
                       3 * f * f, " channels"));
    }
  }

  // An environment.json that says "controllora": false has none to find.
  if (options.lora_policy != LoraPolicy::kSkip && sources.settings.controllora) {
    absl::StatusOr<std::string> lora_path = sources.lora_path.empty()
                                                ? FindLora(files, sources.dir)
                                                : absl::StatusOr<std::string>(sources.lora_path);
    if (lora_path.ok() && !Exists(files, *lora_path)) {
      lora_path = absl::NotFoundError(absl::StrCat("missing ControlLoRA file ", *lora_path));
    }
    if (lora_path.ok()) {
      FD_ASSIGN_OR_RETURN(LoraWeights lora, LoadLoraWeights(*lora_path, files));
      FD_RETURN_IF_ERROR(
          ApplyLora(*env->unet, lora, options.lora_mode, sources.settings.lora_scale));
      env->lora_path = *lora_path;
    } else if (options.lora_policy == LoraPolicy::kRequire) {
      return lora_path.status();
    }
  }

  const std::string scheduler_json = (base / "scheduler" / "scheduler_config.json").string();
  FD_ASSIGN_OR_RETURN(std::string scheduler_text, files.ReadText(scheduler_json));
  FD_ASSIGN_OR_RETURN(env->schedulers,
                      BuildSchedulers(scheduler_text, sources.settings.scheduler, scheduler_json));
  FD_RETURN_IF_ERROR(LoadText(sources, options, *env));
  return env;
}

absl::Status ValidateSettings(const EnvironmentSettings& s, absl::string_view source) {
  if (s.width <= 0 || s.width % 8 != 0) {
    return FieldError(source, "width", "must be a positive multiple of 8");
  }
  if (s.height <= 0 || s.height % 8 != 0) {
    return FieldError(source, "height", "must be a positive multiple of 8");
  }
  if (s.steps < 1) return FieldError(source, "steps", "must be >= 1");
  if (!(s.lora_scale >= 0)) return FieldError(source, "lora_scale", "must be >= 0");
  if (!(s.conditioning_scale >= 0)) {
    return FieldError(source, "conditioning_scale", "must be >= 0");
  }
  if (!(s.guidance_scale >= 1)) return FieldError(source, "guidance_scale", "must be >= 1");
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<std::map<SchedulerType, Scheduler>> BuildSchedulers(std::string_view scheduler_json,
                                                                   SchedulerType required,
                                                                   std::string_view source) {
  std::map<SchedulerType, Scheduler> schedulers;
  for (SchedulerType type : {SchedulerType::kUniPCMultistep, SchedulerType::kDPMSolverMultistep,
                             SchedulerType::kDDIM, SchedulerType::kEulerDiscrete}) {
    absl::StatusOr<SchedulerSettings> settings = SchedulerSettingsFromJson(scheduler_json, type);
    absl::StatusOr<Scheduler> scheduler =
        settings.ok() ? Scheduler::Create(*settings) : absl::StatusOr<Scheduler>(settings.status());
    if (scheduler.ok()) {
      schedulers.emplace(type, *std::move(scheduler));
    } else if (type == required) {
      return absl::Status(scheduler.status().code(),
                          absl::StrCat(absl::string_view(source.data(), source.size()), ": ",
                                       scheduler.status().message()));
    }
  }
  return schedulers;
}

absl::StatusOr<const Scheduler*> Environment::GetScheduler(SchedulerType type) const {
  auto it = schedulers.find(type);
  if (it == schedulers.end()) {
    return absl::NotFoundError(absl::StrCat("environment ", dir, " has no ",
                                            std::string(SchedulerTypeName(type)),
                                            " (unsupported options in its scheduler config)"));
  }
  return &it->second;
}

absl::StatusOr<EnvironmentSettings> ParseEnvironmentSettings(std::string_view json_text_in,
                                                             std::string_view source_in) {
  const absl::string_view json_text(json_text_in.data(), json_text_in.size());
  const absl::string_view source(source_in.data(), source_in.size());
  json j = json::parse(json_text.begin(), json_text.end(), nullptr, /*allow_exceptions=*/false);
  if (j.is_discarded() || !j.is_object()) {
    return absl::InvalidArgumentError(absl::StrCat(source, ": not a JSON object"));
  }
  EnvironmentSettings s;
  FD_RETURN_IF_ERROR(ReadString(j, source, "name", &s.name));
  FD_RETURN_IF_ERROR(ReadString(j, source, "description", &s.description));
  FD_RETURN_IF_ERROR(ReadString(j, source, "prompt", &s.prompt));
  FD_RETURN_IF_ERROR(ReadString(j, source, "negative_prompt", &s.negative_prompt));
  FD_RETURN_IF_ERROR(ReadInt(j, source, "width", &s.width));
  FD_RETURN_IF_ERROR(ReadInt(j, source, "height", &s.height));
  FD_RETURN_IF_ERROR(ReadInt(j, source, "steps", &s.steps));
  FD_RETURN_IF_ERROR(ReadNumber(j, source, "lora_scale", &s.lora_scale));
  FD_RETURN_IF_ERROR(ReadNumber(j, source, "conditioning_scale", &s.conditioning_scale));
  FD_RETURN_IF_ERROR(ReadNumber(j, source, "guidance", &s.guidance_scale));
  FD_RETURN_IF_ERROR(ReadNumber(j, source, "guidance_scale", &s.guidance_scale));
  std::string name;
  if (j.contains("scheduler")) {
    FD_RETURN_IF_ERROR(ReadString(j, source, "scheduler", &name));
    absl::StatusOr<SchedulerType> type = SchedulerTypeFromName(std::string_view(name));
    if (!type.ok()) return FieldError(source, "scheduler", std::string(type.status().message()));
    s.scheduler = *type;
  }
  if (j.contains("sky_mode")) {
    FD_RETURN_IF_ERROR(ReadString(j, source, "sky_mode", &name));
    absl::StatusOr<SkyFillMode> mode = SkyModeFromName(name);
    if (!mode.ok()) return FieldError(source, "sky_mode", std::string(mode.status().message()));
    s.sky_mode = *mode;
  }
  if (j.contains("irradiance")) {
    FD_RETURN_IF_ERROR(ReadString(j, source, "irradiance", &name));
    if (name != "previous_output" && name != "black") {
      return FieldError(source, "irradiance", "must be \"previous_output\" or \"black\"");
    }
    s.irradiance_from_previous = name == "previous_output";
  }
  if (j.contains("controllora")) {
    if (!j["controllora"].is_boolean())
      return FieldError(source, "controllora", "must be a boolean");
    s.controllora = j["controllora"].get<bool>();
  }
  if (j.contains("previous_latent")) {
    FD_RETURN_IF_ERROR(ReadString(j, source, "previous_latent", &name));
    if (name != "encode" && name != "reuse") {
      return FieldError(source, "previous_latent", "must be \"encode\" or \"reuse\"");
    }
    s.reuse_previous_latent = name == "reuse";
  }
  FD_RETURN_IF_ERROR(ValidateSettings(s, source));
  return s;
}

absl::StatusOr<std::shared_ptr<Environment>> LoadEnvironment(const std::string& dir,
                                                             const EnvironmentOptions& options) {
  const FileSource& files = FilesOf(options);
  if (!Exists(files, dir)) return absl::NotFoundError(absl::StrCat("no environment folder ", dir));
  EnvironmentSources sources;
  sources.dir = dir;
  sources.base_dir = dir;
  sources.controlnet_dir = (fs::path(dir) / "controlnet").string();
  const std::string settings_path = (fs::path(dir) / "environment.json").string();
  if (Exists(files, settings_path)) {
    FD_ASSIGN_OR_RETURN(std::string text, files.ReadText(settings_path));
    FD_ASSIGN_OR_RETURN(sources.settings, ParseEnvironmentSettings(text, settings_path));
  }
  if (sources.settings.name.empty()) sources.settings.name = fs::path(dir).filename().string();
  return LoadFromSources(sources, options);
}

absl::StatusOr<std::vector<InferenceConfigEntry>> ParseInferenceConfigs(
    std::string_view json_text, const std::string& base_dir) {
  json j = json::parse(json_text.begin(), json_text.end(), nullptr, /*allow_exceptions=*/false);
  if (j.is_discarded() || !j.is_object()) {
    return absl::InvalidArgumentError("inference configs: not a JSON object");
  }
  auto resolve = [&](const std::string& path) {
    fs::path p(path);
    return p.is_absolute() ? p.string() : (fs::path(base_dir) / p).lexically_normal().string();
  };
  std::vector<InferenceConfigEntry> entries;
  for (const auto& [key, value] : j.items()) {
    const std::string source = absl::StrCat("inference configs entry '", key, "'");
    if (!value.is_object()) return absl::InvalidArgumentError(source + ": not an object");
    InferenceConfigEntry entry;
    entry.name = key;
    for (const char* required : {"controlnet_path", "controllora_path", "prompt"}) {
      if (!value.contains(required)) return FieldError(source, required, "is missing");
    }
    FD_RETURN_IF_ERROR(ReadString(value, source, "controlnet_path", &entry.controlnet_path));
    FD_RETURN_IF_ERROR(ReadString(value, source, "controllora_path", &entry.controllora_path));
    FD_RETURN_IF_ERROR(ReadString(value, source, "prompt", &entry.prompt));
    FD_RETURN_IF_ERROR(ReadString(value, source, "negative_prompt", &entry.negative_prompt));
    if (value.contains("enable_injection")) {
      if (!value["enable_injection"].is_boolean()) {
        return FieldError(source, "enable_injection", "must be a boolean");
      }
      entry.enable_injection = value["enable_injection"].get<bool>();
    }
    entry.controlnet_path = resolve(entry.controlnet_path);
    entry.controllora_path = resolve(entry.controllora_path);
    entries.push_back(std::move(entry));
  }
  return entries;
}

absl::StatusOr<std::vector<InferenceConfigEntry>> LoadInferenceConfigs(const std::string& path) {
  FD_ASSIGN_OR_RETURN(std::string text, DiskFiles().ReadText(path));
  return ParseInferenceConfigs(text, fs::path(path).parent_path().string());
}

absl::StatusOr<std::shared_ptr<Environment>> LoadEnvironmentFromInferenceConfig(
    const InferenceConfigEntry& entry, const std::string& base_dir,
    const EnvironmentOptions& options) {
  EnvironmentSources sources;
  sources.dir = fs::path(entry.controlnet_path).parent_path().string();
  sources.base_dir = base_dir;
  sources.controlnet_dir = entry.controlnet_path;
  sources.lora_path = entry.controllora_path;
  sources.settings.name = entry.name;
  sources.settings.prompt = entry.prompt;
  sources.settings.negative_prompt = entry.negative_prompt;
  sources.settings.sky_mode = entry.enable_injection ? SkyFillMode::kSkyImage : SkyFillMode::kNone;
  return LoadFromSources(sources, options);
}

}  // namespace fd::model

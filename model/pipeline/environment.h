// An "environment": one trained FrameDiffuser model (a scene / art style) with
// everything a frame needs that does not change from frame to frame: the
// networks (UNet with its ControlLoRA, ControlNet, VAE), the schedulers built
// from the checkpoint's scheduler config, the prompt embeddings (computed
// once), and the per-environment defaults (resolution, steps, sky mode...).
//
// Folder layout (the authors' checkpoint layout, cgtuebingen/FrameDiffuser
// README + train.py, plus SD1.5's base parts):
//   unet/         config.json + diffusion_pytorch_model.safetensors
//   vae/          config.json + diffusion_pytorch_model.safetensors
//   controlnet/   config.json + diffusion_pytorch_model.safetensors
//   scheduler/    scheduler_config.json (SD1.5's PNDM json is fine: the
//                 sampler class is chosen here, as inference.py does with
//                 UniPCMultistepScheduler.from_config(...))
//   text_encoder/ + tokenizer/   (optional) SD1.5 CLIP text encoder
//   prompt_embeds.safetensors    (optional) precomputed `prompt_embeds`
//                                [1, T, D]; used instead of the text encoder
//                                when present
//   negative_prompt_embeds.safetensors (optional) for guidance > 1 without
//                                a text encoder
//   the ControlLoRA file, the first that exists of kLoraFileCandidates
//   environment.json             (optional) EnvironmentSettings
//
// The authors' `inference_configs.json` (one entry per environment with
// controlnet_path, controllora_path, prompt, negative_prompt,
// enable_injection; paths relative to the json's folder) is imported by
// ParseInferenceConfigs + LoadEnvironmentFromInferenceConfig, with the SD1.5
// base parts taken from a separate folder (the GUI downloads
// runwayml/stable-diffusion-v1-5).
#ifndef FD_MODEL_PIPELINE_ENVIRONMENT_H_
#define FD_MODEL_PIPELINE_ENVIRONMENT_H_

#include <torch/types.h>

#include <map>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "model/checkpoint/file_source.h"
#include "model/lora/apply_lora.h"
#include "model/networks/controlnet.h"
#include "model/networks/unet.h"
#include "model/networks/vae.h"
#include "model/pipeline/conditioning.h"
#include "model/schedulers/scheduler.h"
#include "model/schedulers/scheduler_settings.h"

namespace fd::model {

// Where the ControlLoRA file may sit, relative to the environment folder, in
// search order (README: `controllora.safetensors`; inference_configs.json:
// `pytorch_lora_weights.safetensors`; the golden fd_pipeline checkpoint:
// `controllora/pytorch_lora_weights.safetensors`; the A/B goldens:
// `unet_lora/...`).
inline constexpr const char* kLoraFileCandidates[] = {
    "controllora/pytorch_lora_weights.safetensors",
    "controllora/controllora.safetensors",
    "controllora.safetensors",
    "pytorch_lora_weights.safetensors",
    "unet_lora/pytorch_lora_weights.safetensors",
};

// environment.json. Defaults = the authors' GUI inference (inference.py):
// UniPC, 10 steps, guidance 1.0, LoRA (extra condition) scale 1.0,
// ControlNet conditioning scale 1.0, 512x512, sky injection on.
struct EnvironmentSettings {
  std::string name;
  std::string description;
  std::string prompt;
  std::string negative_prompt;  // used only when guidance_scale > 1
  int width = 512;
  int height = 512;
  int steps = 10;
  SchedulerType scheduler = SchedulerType::kUniPCMultistep;
  SkyFillMode sky_mode = SkyFillMode::kSkyImage;  // enable_injection = true
  double lora_scale = 1.0;
  double conditioning_scale = 1.0;
  double guidance_scale = 1.0;
  // "irradiance": "previous_output" (the paper) or "black" (a model trained
  // without it: channel 9 stays black at inference too).
  bool irradiance_from_previous = true;
  // "controllora": false for a model without one (stage 1 alone, the
  // X->RGB setting): LoadEnvironment then does not look for it.
  bool controllora = true;
  // "previous_latent": "encode" (the authors': the VAE encodes the previous
  // output frame, one posterior sample) or "reuse" (the previous frame's
  // denoised latent is taken as it is, skipping the encoder: a serving
  // speed-up, not the reference's arithmetic; the session layer keeps the
  // latent, see session/session_state.h). Keyframes are always encoded.
  bool reuse_previous_latent = false;
};

// Parses environment.json text. Keys (all optional): name, description,
// prompt, negative_prompt, width, height, steps, scheduler ("unipc",
// "dpmsolver++", "ddim", "euler" or a diffusers class name), sky_mode
// ("sky_image", "previous_output", "none"), lora_scale, conditioning_scale,
// guidance_scale (alias "guidance"), irradiance ("previous_output" or
// "black"), controllora (bool), previous_latent ("encode" or "reuse").
// Unknown keys are ignored.
// Errors: INVALID_ARGUMENT naming `source` and the field (bad json, wrong
// type, width/height not positive multiples of 8, steps < 1, negative
// scales, guidance < 1, unknown scheduler / sky mode / previous_latent).
absl::StatusOr<EnvironmentSettings> ParseEnvironmentSettings(std::string_view json_text,
                                                             std::string_view source);

// What to do with the ControlLoRA.
enum class LoraPolicy {
  kRequire,  // NOT_FOUND when no ControlLoRA file is found (default)
  kIfPresent,
  kSkip,  // load the UNet without LoRA
};

struct EnvironmentOptions {
  torch::Device device = torch::kCPU;
  torch::Dtype dtype = torch::kFloat32;  // float32 | float16 | bfloat16
  // Live (unmerged, the authors' inference) or merged into the weights.
  LoraMode lora_mode = LoraMode::kLive;
  LoraPolicy lora_policy = LoraPolicy::kRequire;
  // false: NOT_FOUND when the folder has neither text_encoder/+tokenizer/
  // nor prompt_embeds.safetensors. true: load without prompt embeddings
  // (every frame request must then carry its own prompt_embeds).
  bool allow_missing_text = false;
  // Where the folder's files are read from; nullptr: the file system. A
  // MemoryFiles (model/checkpoint/file_source.h) loads an environment held in
  // memory (compiled into a binary) without writing it anywhere. Borrowed:
  // must outlive the LoadEnvironment call.
  const FileSource* files = nullptr;
};

// A loaded environment. Ownership: shared (std::shared_ptr) by the sessions
// using it. Thread-safety: immutable after loading; the networks may run
// concurrently (see unet.h etc.). Nobody may change LoRA scales or weights
// while frames are rendered.
struct Environment {
  std::string dir;  // folder it was loaded from (for messages)
  EnvironmentSettings settings;
  torch::Device device = torch::kCPU;
  torch::Dtype dtype = torch::kFloat32;

  UNet2DConditionModel unet{nullptr};
  ControlNetModel controlnet{nullptr};
  AutoencoderKL vae{nullptr};
  std::string lora_path;  // empty when no LoRA is applied
  LoraMode lora_mode = LoraMode::kLive;

  // One scheduler per sampler type that the scheduler config supports (the
  // type of `settings.scheduler` is always present).
  std::map<SchedulerType, Scheduler> schedulers;

  // [1, T, D] float32 on `device`; undefined when loaded with
  // allow_missing_text and no text source.
  torch::Tensor prompt_embeds;
  // [1, T, D] for guidance > 1: the encoded negative prompt ("" when unset)
  // or negative_prompt_embeds.safetensors; undefined when unavailable.
  torch::Tensor negative_prompt_embeds;

  // NOT_FOUND when this environment has no scheduler of `type`.
  absl::StatusOr<const Scheduler*> GetScheduler(SchedulerType type) const;
};

// One scheduler per sampler type that `scheduler_json` (a diffusers
// scheduler_config.json text) supports. Errors: the `required` type's
// INVALID_ARGUMENT / UNIMPLEMENTED, prefixed with `source`; other types are
// left out silently.
absl::StatusOr<std::map<SchedulerType, Scheduler>> BuildSchedulers(std::string_view scheduler_json,
                                                                   SchedulerType required,
                                                                   std::string_view source);

// Loads an environment folder (layout above). environment.json is optional
// (defaults apply). Errors: NOT_FOUND naming the missing file or folder
// (including the list of ControlLoRA places searched); INVALID_ARGUMENT
// naming the bad field or tensor (environment.json, configs, weights, LoRA
// shapes, a prompt_embeds width that is not the UNet's
// cross_attention_dim); UNIMPLEMENTED / INTERNAL from the loaders.
// With options.files set, `dir` is a path in that source (e.g. its root).
absl::StatusOr<std::shared_ptr<Environment>> LoadEnvironment(
    const std::string& dir, const EnvironmentOptions& options = {});

// One entry of the authors' inference_configs.json.
struct InferenceConfigEntry {
  std::string name;              // the json key, e.g. "DowntownWest"
  std::string controlnet_path;   // resolved against the json's folder
  std::string controllora_path;  // a .safetensors file (resolved)
  std::string prompt;
  std::string negative_prompt;
  bool enable_injection = true;
};

// Parses inference_configs.json text; relative paths are resolved against
// `base_dir`. Other keys (gbuffer_dir, output_dir, ...) are ignored.
// Errors: INVALID_ARGUMENT naming the entry and field (bad json, missing
// controlnet_path / controllora_path / prompt, wrong types).
absl::StatusOr<std::vector<InferenceConfigEntry>> ParseInferenceConfigs(
    std::string_view json_text, const std::string& base_dir);
// Reads and parses a file (base_dir = its folder). NOT_FOUND if missing.
absl::StatusOr<std::vector<InferenceConfigEntry>> LoadInferenceConfigs(const std::string& path);

// Builds an environment from an inference_configs.json entry: unet/, vae/,
// scheduler/ and the text source (text_encoder/+tokenizer/ or
// prompt_embeds.safetensors) come from `base_dir` (an SD1.5 folder), the
// ControlNet and ControlLoRA from the entry; settings are the defaults with
// the entry's name, prompt, negative prompt and sky mode (injection on ->
// kSkyImage, off -> kNone). Errors as LoadEnvironment.
absl::StatusOr<std::shared_ptr<Environment>> LoadEnvironmentFromInferenceConfig(
    const InferenceConfigEntry& entry, const std::string& base_dir,
    const EnvironmentOptions& options = {});

}  // namespace fd::model

#endif  // FD_MODEL_PIPELINE_ENVIRONMENT_H_

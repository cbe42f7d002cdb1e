// The training loop and stage transitions; see trainer.h. Checkpoints and
// export: trainer_checkpoint.cc.
#include "trainer/trainer.h"

#include <ATen/CPUGeneratorImpl.h>
#include <ATen/autocast_mode.h>
#include <torch/torch.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <future>
#include <map>
#include <set>
#include <utility>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "base/status_macros.h"
#include "client_sdk/image_io.h"
#include "model/checkpoint/checkpoint_writer.h"
#include "model/checkpoint/state_dict_loader.h"
#include "model/networks/gradient_checkpoint.h"
#include "model/networks/model_configs.h"
#include "model/pipeline/conditioning.h"
#include "model/pipeline/frame_pipeline.h"
#include "model/presets/presets.h"
#include "model/presets/training_init.h"
#include "model/runtime/torch_call.h"
#include "model/schedulers/scheduler.h"
#include "model/text/clip_text_model.h"
#include "model/text/clip_tokenizer.h"
#include "trainer/file_io.h"
#include "trainer/lr_schedule.h"

namespace fd::trainer {
namespace {

namespace fs = std::filesystem;
using fd::model::SchedulerType;
using fd::model::TorchCall;  // torch exceptions -> INTERNAL

// --dtype bfloat16 on CUDA: the forward runs under autocast (bf16 matmuls
// and convolutions, float32 masters, gradients and loss), as accelerate's
// mixed_precision="bf16" does for the authors. A no-op otherwise.
class AutocastScope {
 public:
  explicit AutocastScope(bool enabled) : enabled_(enabled) {
    if (!enabled_) return;
    previous_ = at::autocast::is_enabled();
    at::autocast::set_autocast_gpu_dtype(at::kBFloat16);
    at::autocast::set_enabled(true);
  }
  ~AutocastScope() {
    if (!enabled_) return;
    at::autocast::set_enabled(previous_);
    at::autocast::clear_cache();
  }
  AutocastScope(const AutocastScope&) = delete;
  AutocastScope& operator=(const AutocastScope&) = delete;

 private:
  bool enabled_;
  bool previous_ = false;
};

// The stage a stage builds on (stage 0a has none). The optional decoder
// fine-tune needs only the VAE, and stage 0b does not need it.
std::optional<Stage> Predecessor(Stage stage) {
  switch (stage) {
    case Stage::kVae:
      return std::nullopt;
    case Stage::kDecoder:
    case Stage::kBase:
      return Stage::kVae;
    default:
      return static_cast<Stage>(static_cast<int>(stage) - 1);
  }
}

}  // namespace

StageSchedule DefaultSchedule(Stage stage) {
  // Step counts for the tiny preset at 64x64 on 2 CPU cores (trainer
  // benchmark, docs/BENCHMARKS.md); warm-up 5 % as stage 1 of the .bat.
  switch (stage) {
    case Stage::kVae:
      return {1500, 75, 1e-3, 0};
    case Stage::kBase:
      return {2000, 100, 5e-4, 0};
    case Stage::kControlNet:
      return {1500, 75, 2e-4, 0};
    case Stage::kControlLora:
      // The .bat: stage 2's LoRA lr is 10x stage 1's.
      return {1000, 100, 1e-3, 0};
    case Stage::kSelfConditioning:
      return {1000, 33, 2.5e-4, 1e-4};
    case Stage::kDecoder:
      // Off unless --decoder_steps is given; a fine-tune, so a fifth of stage
      // 0a's rate, 5 % warm-up.
      return {0, 0, 2e-4, 0};
  }
  return {};
}

Trainer::Trainer(TrainerOptions options) : options_(std::move(options)) {}
Trainer::~Trainer() = default;

absl::StatusOr<std::unique_ptr<Trainer>> Trainer::Create(TrainerOptions options) {
  if (options.out_dir.empty()) return absl::InvalidArgumentError("--out is required");
  if (options.batch_size < 1) return absl::InvalidArgumentError("--batch_size must be >= 1");
  if (options.grad_accum < 1) return absl::InvalidArgumentError("--grad_accum must be >= 1");
  if (options.max_offset < 1) return absl::InvalidArgumentError("--max_offset must be >= 1");
  if (options.max_noise_sigma < 0)
    return absl::InvalidArgumentError("--max_noise_sigma must be >= 0");
  if (options.max_blur_sigma < 0) {
    return absl::InvalidArgumentError("--max_blur_sigma must be >= 0");
  }
  if (options.pixel_loss_weight < 0) {
    return absl::InvalidArgumentError("--pixel_loss_weight must be >= 0");
  }
  if (options.ema_decay < 0 || options.ema_decay >= 1) {
    return absl::InvalidArgumentError("--ema_decay must be in [0, 1)");
  }
  if (options.colour_latent_scale < 0) {
    return absl::InvalidArgumentError("--colour_latent_scale must be >= 0");
  }
  if (options.colour_latent_scale > 0 && (!options.vae_dir.empty() || !options.base_dir.empty())) {
    return absl::InvalidArgumentError(
        "--colour_latent_scale trains stage 0's VAE; --vae and --base bring their own");
  }
  if (options.colour_latent_scale > 0 && options.latent_channels > 0 &&
      options.latent_channels < kColourLatentChannels + 1) {
    return absl::InvalidArgumentError(
        "--colour_latent_scale needs --latent_channels >= 4 (three tied to the colour)");
  }
  if (options.recolour_probability < 0 || options.recolour_probability > 1) {
    return absl::InvalidArgumentError("--recolour_probability must be in [0, 1]");
  }
  if (options.flip_probability < 0 || options.flip_probability > 1) {
    return absl::InvalidArgumentError("--flip_probability must be in [0, 1]");
  }
  if (options.flip_probability > 0 && !options.flip_plane_normal.has_value()) {
    return absl::InvalidArgumentError(
        "--flip_probability needs --flip_plane_normal X,Y,Z: the plane the world-space normals "
        "are reflected in (a vertical plane through the sun's direction; 1,0,0 for camera-space "
        "normals)");
  }
  if (options.flip_plane_normal.has_value()) {
    const auto& n = *options.flip_plane_normal;
    const double norm = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
    if (!std::isfinite(norm) || std::abs(norm - 1.0) > 1e-6) {
      return absl::InvalidArgumentError("--flip_plane_normal must be a unit vector");
    }
  }
  if (options.selfcond_ratio < 0 || options.selfcond_ratio > 1) {
    return absl::InvalidArgumentError("--selfcond_ratio must be in [0, 1]");
  }
  if (options.selfcond_chain_ratio < 0 || options.selfcond_chain_ratio > 1) {
    return absl::InvalidArgumentError("--selfcond_chain_ratio must be in [0, 1]");
  }
  if (options.selfcond_steps < 1)
    return absl::InvalidArgumentError("--selfcond_steps must be >= 1");
  if (options.vae_crop != 0 &&
      (options.vae_crop % 8 != 0 || options.vae_crop > std::min(options.width, options.height))) {
    return absl::InvalidArgumentError(
        "--vae_crop must be a multiple of 8 and at most the training resolution");
  }
  if (options.latent_channels < 0) {
    return absl::InvalidArgumentError("--latent_channels must be >= 1");
  }
  if (options.latent_channels > 0 && !options.base_dir.empty()) {
    return absl::InvalidArgumentError(
        "--latent_channels sets fresh networks' widths; --base brings its own VAE");
  }
  if (!options.vae_dir.empty() && !options.base_dir.empty()) {
    return absl::InvalidArgumentError("--vae replaces stage 0's VAE; --base brings its own VAE");
  }
  if (!options.vae_dir.empty() && options.latent_channels > 0) {
    return absl::InvalidArgumentError(
        "--latent_channels sets a fresh VAE's latent; --vae brings its own");
  }
  if (!options.prediction_type.empty() && !options.base_dir.empty()) {
    return absl::InvalidArgumentError(
        "--prediction_type sets fresh networks' objective; --base brings its own scheduler "
        "config (its prediction_type)");
  }
  if (!options.decoder_latents_from.empty()) {
    if (options.schedule[static_cast<int>(Stage::kDecoder)].steps < 1) {
      return absl::InvalidArgumentError(
          "--decoder_latents_from feeds the decoder fine-tune; give --decoder_steps N");
    }
    if (options.vae_dir.empty()) {
      return absl::InvalidArgumentError(absl::StrCat(
          "--decoder_latents_from fine-tunes that environment's decoder; give --vae ",
          options.decoder_latents_from.size() > 64 ? "ENV" : options.decoder_latents_from));
    }
    if (options.decoder_chains < 1 || options.decoder_chain_frames < 1) {
      return absl::InvalidArgumentError("--decoder_chains and --decoder_chain_frames must be >= 1");
    }
  }
  if (options.dtype != torch::kFloat32 && !options.device.is_cuda()) {
    return absl::InvalidArgumentError(
        "--dtype bfloat16 (mixed precision) needs --device cuda:N; on the CPU train in float32");
  }
  const bool decoder_on = options.schedule[static_cast<int>(Stage::kDecoder)].steps > 0;
  for (int s = 0; s < kStageCount; ++s) {
    const StageSchedule& sched = options.schedule[s];
    if (static_cast<Stage>(s) == Stage::kDecoder && !decoder_on) continue;  // off
    if (sched.steps < 1 || sched.warmup < 0 || sched.warmup > sched.steps || sched.lr <= 0) {
      return absl::InvalidArgumentError(absl::StrCat(
          StageName(static_cast<Stage>(s)), ": steps must be >= 1, 0 <= warmup <= steps, lr > 0"));
    }
  }
  if (options.stages.empty()) options.stages.assign(kRunOrder.begin(), kRunOrder.end());
  if (!decoder_on) {
    if (options.stages == std::vector<Stage>{Stage::kDecoder}) {
      return absl::InvalidArgumentError(
          "stage0-decoder needs --decoder_steps N (the decoder fine-tune is off by default)");
    }
    // `all` and `stage0` run the fine-tune only when it has steps.
    options.stages.erase(std::remove(options.stages.begin(), options.stages.end(), Stage::kDecoder),
                         options.stages.end());
  }
  std::unique_ptr<Trainer> trainer(new Trainer(std::move(options)));
  FD_RETURN_IF_ERROR(trainer->Init());
  return trainer;
}

absl::Status Trainer::Init() {
  torch::set_num_threads(std::max(1, options_.threads));
  TrainingDataOptions data_options;
  data_options.width = options_.width;
  data_options.height = options_.height;
  data_options.max_offset = options_.max_offset;
  data_options.exr_values = options_.exr_values;
  FD_ASSIGN_OR_RETURN(data_, LoadTrainingData(options_.data_dirs, data_options));
  if (!options_.validation_dirs.empty()) {
    FD_ASSIGN_OR_RETURN(validation_data_, LoadTrainingData(options_.validation_dirs, data_options));
  }
  FD_ASSIGN_OR_RETURN(log_, RunLog::Open((fs::path(options_.out_dir) / "train").string(),
                                         options_.progress_bar, options_.log_every));
  FD_RETURN_IF_ERROR(LoadBase());

  const std::string latest = (fs::path(options_.out_dir) / "checkpoints" / "LATEST").string();
  if (PathExists(latest)) {
    FD_ASSIGN_OR_RETURN(std::string name, ReadTextFile(latest));
    while (!name.empty() && (name.back() == '\n' || name.back() == ' ')) name.pop_back();
    FD_RETURN_IF_ERROR(
        LoadCheckpoint((fs::path(options_.out_dir) / "checkpoints" / name).string()));
    // The folder's UNet config fixed the basecolor patches when stage 0 ran.
    FD_ASSIGN_OR_RETURN(fd::model::UNet2DConditionConfig saved,
                        fd::model::ParseUNet2DConditionConfig(unet_json_, "unet config"));
    if (saved.basecolor_patch_channels != basecolor_patch_channels_) {
      return absl::FailedPreconditionError(absl::StrCat(
          "--out ", options_.out_dir, " was trained ",
          saved.basecolor_patch_channels > 0 ? "with --basecolor_patches; give it again"
                                             : "without --basecolor_patches; leave it out",
          " (or start a new --out)"));
    }
  }
  if (!options_.command_line.empty() &&
      (commands_.empty() || commands_.back() != options_.command_line)) {
    commands_.push_back(options_.command_line);
  }
  log_->Event("start", {{"frames", data_.frame_count()},
                        {"sequences", data_.sequences.size()},
                        {"validation_frames", validation_data_.frame_count()},
                        {"resolution", absl::StrCat(options_.width, "x", options_.height)},
                        {"preset", options_.preset},
                        {"threads", options_.threads}});
  return absl::OkStatus();
}

absl::Status Trainer::LoadBase() {
  FD_ASSIGN_OR_RETURN(fd::model::PresetConfigs preset,
                      fd::model::GetPresetConfigs(options_.preset));
  lora_rank_ = options_.lora_rank > 0 ? options_.lora_rank : preset.lora_rank;
  FD_ASSIGN_OR_RETURN(fd::model::ControlNetConfig preset_cn,
                      fd::model::ParseControlNetConfig(preset.controlnet, "preset controlnet"));
  controlnet_embedding_channels_ = preset_cn.conditioning_embedding_out_channels;
  if (options_.base_dir.empty()) {
    unet_json_ = preset.unet;
    vae_json_ = preset.vae;
    if (options_.latent_channels > 0) {
      nlohmann::json unet = nlohmann::json::parse(unet_json_);
      unet["in_channels"] = options_.latent_channels;
      unet["out_channels"] = options_.latent_channels;
      unet_json_ = unet.dump(2) + "\n";
      nlohmann::json vae = nlohmann::json::parse(vae_json_);
      vae["latent_channels"] = options_.latent_channels;
      vae_json_ = vae.dump(2) + "\n";
    }
    nlohmann::json scheduler = nlohmann::json::parse(fd::model::kSd15SchedulerConfigJson);
    if (!options_.prediction_type.empty()) scheduler["prediction_type"] = options_.prediction_type;
    scheduler_json_ = scheduler.dump(2) + "\n";
    if (!options_.vae_dir.empty()) FD_RETURN_IF_ERROR(LoadTrainedVae());
  } else {
    // A diffusers SD folder, as the authors start from SD1.5: its UNet
    // (4-channel conv_in), VAE, scheduler and text.
    const fs::path base(options_.base_dir);
    FD_ASSIGN_OR_RETURN(unet_json_, ReadTextFile((base / "unet" / "config.json").string()));
    FD_ASSIGN_OR_RETURN(vae_json_, ReadTextFile((base / "vae" / "config.json").string()));
    FD_ASSIGN_OR_RETURN(scheduler_json_,
                        ReadTextFile((base / "scheduler" / "scheduler_config.json").string()));
    FD_ASSIGN_OR_RETURN(
        unet_, fd::model::LoadUNet((base / "unet").string(), options_.device, torch::kFloat32,
                                   /*frame_diffuser_input=*/false));
    FD_ASSIGN_OR_RETURN(
        vae_, fd::model::LoadVae((base / "vae").string(), options_.device, torch::kFloat32));
    const std::string embeds = (base / "prompt_embeds.safetensors").string();
    if (PathExists(embeds)) {
      FD_ASSIGN_OR_RETURN(prompt_embeds_, fd::model::LoadPromptEmbeds(embeds));
    } else if (PathExists((base / "text_encoder").string())) {
      FD_ASSIGN_OR_RETURN(fd::model::ClipTokenizer tokenizer,
                          fd::model::ClipTokenizer::FromDirectory((base / "tokenizer").string()));
      FD_ASSIGN_OR_RETURN(fd::model::ClipTextModel encoder,
                          fd::model::LoadClipTextModel((base / "text_encoder").string(),
                                                       options_.device, torch::kFloat32));
      FD_ASSIGN_OR_RETURN(prompt_embeds_,
                          fd::model::EncodePrompts(tokenizer, encoder, {options_.prompt}));
    } else {
      return absl::NotFoundError(absl::StrCat("--base ", options_.base_dir,
                                              " has neither prompt_embeds.safetensors nor "
                                              "text_encoder/ + tokenizer/"));
    }
    prompt_embeds_ = prompt_embeds_.to(options_.device, torch::kFloat32);
    completed_[static_cast<int>(Stage::kVae)] = true;
    completed_[static_cast<int>(Stage::kBase)] = true;
  }
  FD_ASSIGN_OR_RETURN(fd::model::SchedulerSettings settings,
                      fd::model::SchedulerSettingsFromJson(scheduler_json_, SchedulerType::kDDIM));
  FD_ASSIGN_OR_RETURN(fd::model::Scheduler training_schedule,
                      fd::model::Scheduler::Create(settings));
  // DDPMScheduler.from_pretrained(SD1.5): the same betas as every sampler.
  alphas_cumprod_ = training_schedule.alphas_cumprod().clone();
  prediction_type_ = settings.prediction_type;
  if (options_.basecolor_patches) {
    FD_ASSIGN_OR_RETURN(fd::model::AutoencoderKLConfig vae_config,
                        fd::model::ParseAutoencoderKLConfig(vae_json_, "vae config"));
    const int64_t f = int64_t{1} << (vae_config.block_out_channels.size() - 1);
    basecolor_patch_channels_ = 3 * f * f;
    nlohmann::json unet = nlohmann::json::parse(unet_json_);
    unet["basecolor_patch_channels"] = basecolor_patch_channels_;
    unet_json_ = unet.dump(2) + "\n";
  }
  FD_ASSIGN_OR_RETURN(controlnet_json_, fd::model::ControlNetConfigJsonFromUNet(
                                            unet_json_, controlnet_embedding_channels_));
  return absl::OkStatus();
}

const StageSchedule& Trainer::schedule() const {
  return options_.schedule[static_cast<int>(*stage_)];
}

int64_t Trainer::SelfcondEvery() const {
  if (options_.selfcond_every > 0) return options_.selfcond_every;
  // train_3_stages.bat: every 2000 of 30000 steps (14 rounds).
  return std::max<int64_t>(
      1, options_.schedule[static_cast<int>(Stage::kSelfConditioning)].steps / 15);
}

double Trainer::loader_wait_fraction() const {
  return step_seconds_ > 0 ? wait_seconds_ / step_seconds_ : 0.0;
}

absl::Status Trainer::Run() {
  for (Stage stage : options_.stages) {
    if (completed(stage)) {
      log_->Event("skip", {{"stage", StageName(stage)},
                           {"why", FromVaeDir(stage) ? "the autoencoder of --vae"
                                                     : "already trained in --out"}});
      continue;
    }
    if (!stage_ || *stage_ != stage) {
      if (stage_) {
        return absl::FailedPreconditionError(absl::StrCat(
            "--out has an unfinished ", StageName(*stage_), "; run it (with --resume) first"));
      }
      const std::optional<Stage> before = Predecessor(stage);
      if (before && !completed(*before)) {
        return absl::FailedPreconditionError(absl::StrCat(
            StageName(stage), " needs ", StageName(*before), " first (framediffuser-train ",
            StageName(*before), " --out ", options_.out_dir, ")"));
      }
      FD_RETURN_IF_ERROR(BeginStage(stage));
    }
    const bool selfcond = stage == Stage::kSelfConditioning;
    trained_this_run_ = true;
    while (step_ < schedule().steps) {
      if (selfcond && step_ > 0 && step_ % SelfcondEvery() == 0 && pool_step_ != step_) {
        FD_RETURN_IF_ERROR(GeneratePool());
      }
      FD_RETURN_IF_ERROR(TrainStep().status());
      const bool last = step_ == schedule().steps;
      if (!last && options_.checkpoint_every > 0 && step_ % options_.checkpoint_every == 0) {
        FD_RETURN_IF_ERROR(SaveCheckpoint());
      }
      if (!last && options_.validate_every > 0 && step_ % options_.validate_every == 0 &&
          stage != Stage::kVae && stage != Stage::kDecoder && stage != Stage::kBase) {
        FD_RETURN_IF_ERROR(Validate().status());
      }
      if (!last && options_.stop_requested && options_.stop_requested()) {
        FD_RETURN_IF_ERROR(SaveCheckpoint());
        log_->Event("interrupted", {{"stage", StageName(stage)}, {"step", step_}});
        return absl::CancelledError(absl::StrCat("interrupted in ", StageName(stage), " at step ",
                                                 step_, "; continue with --resume"));
      }
    }
    FD_RETURN_IF_ERROR(EndStage());
  }
  // A run that only skipped finished stages still refreshes the export
  // (environment.json's record names this command too).
  if (!trained_this_run_ &&
      std::any_of(completed_.begin(), completed_.end(), [](bool done) { return done; })) {
    FD_RETURN_IF_ERROR(ExportEnvironment());
  }
  return absl::OkStatus();
}

absl::Status Trainer::BeginStage(Stage stage) {
  if (stage_) {
    return absl::FailedPreconditionError(
        absl::StrCat("BeginStage: ", StageName(*stage_), " is still running"));
  }
  const uint64_t seed = MixSeed(options_.seed, static_cast<uint64_t>(stage), 1ULL << 63);
  switch (stage) {
    case Stage::kVae: {
      FD_ASSIGN_OR_RETURN(fd::model::AutoencoderKLConfig config,
                          fd::model::ParseAutoencoderKLConfig(vae_json_, "vae config"));
      FD_ASSIGN_OR_RETURN(vae_, fd::model::MakeVae(config));
      FD_RETURN_IF_ERROR(fd::model::InitializeDefaultWeights(*vae_, seed));
      FD_RETURN_IF_ERROR(TorchCall("vae to device", [&]() -> absl::Status {
        vae_->to(options_.device);
        return absl::OkStatus();
      }));
      break;
    }
    case Stage::kDecoder:
      if (!vae_) return absl::FailedPreconditionError("stage0-decoder needs the VAE (stage0-vae)");
      break;
    case Stage::kBase: {
      if (!vae_) return absl::FailedPreconditionError("stage0-base needs the VAE (stage0-vae)");
      FD_ASSIGN_OR_RETURN(fd::model::UNet2DConditionConfig config,
                          fd::model::ParseUNet2DConditionConfig(unet_json_, "unet config"));
      config.conv_in_channels = config.out_channels;  // the base UNet: noisy latent only
      FD_ASSIGN_OR_RETURN(unet_, fd::model::MakeUNet(config));
      FD_RETURN_IF_ERROR(fd::model::InitializeDefaultWeights(*unet_, seed));
      FD_RETURN_IF_ERROR(TorchCall("prompt embedding", [&]() -> absl::Status {
        unet_->to(options_.device);
        // No text encoder is trained: the environment's fixed prompt is a
        // fixed embedding [1, 77, D] (what encoding one constant prompt gives).
        at::Generator gen = at::make_generator<at::CPUGeneratorImpl>(seed + 1);
        prompt_embeds_ =
            torch::randn({1, 77, config.cross_attention_dim.at(0)}, gen).to(options_.device);
        return absl::OkStatus();
      }));
      break;
    }
    case Stage::kControlNet: {
      if (!unet_) return absl::FailedPreconditionError("stage1 needs a base UNet");
      FD_ASSIGN_OR_RETURN(fd::model::ControlNetConfig config,
                          fd::model::ParseControlNetConfig(controlnet_json_, "controlnet config"));
      FD_ASSIGN_OR_RETURN(controlnet_, fd::model::ControlNetFromUNet(*unet_, config, seed));
      if (basecolor_patch_channels_ > 0 &&
          unet_->input_channels() == unet_->config().out_channels) {
        // The basecolor patches enter with the G-buffer, in stage 1 (the
        // previous-latent channels stay zero until stage 2).
        FD_ASSIGN_OR_RETURN(unet_, fd::model::WidenConvIn(*unet_, basecolor_patch_channels_));
      }
      break;
    }
    case Stage::kControlLora: {
      if (!controlnet_) return absl::FailedPreconditionError("stage2 needs the stage-1 ControlNet");
      if (unet_->input_channels() == unet_->config().out_channels) {
        FD_ASSIGN_OR_RETURN(unet_, fd::model::WidenConvIn(*unet_, basecolor_patch_channels_));
      }
      if (!has_lora_) {
        FD_RETURN_IF_ERROR(fd::model::AddTrainableControlLora(*unet_, lora_rank_, seed).status());
        has_lora_ = true;
      }
      break;
    }
    case Stage::kSelfConditioning:
      if (!has_lora_) return absl::FailedPreconditionError("stage3 needs the stage-2 ControlLoRA");
      pool_.clear();
      pool_step_ = -1;
      break;
  }
  stage_ = stage;
  step_ = 0;
  step_seconds_ = 0;
  wait_seconds_ = 0;
  stage_seconds_before_ = 0;
  stage_clock_ = std::chrono::steady_clock::now();
  log_->Event("stage_start", {{"stage", StageName(stage)}, {"steps", schedule().steps}});
  return ConfigureStage(stage);
}

absl::StatusOr<std::vector<std::vector<torch::Tensor>>> Trainer::TrainableGroups(Stage stage,
                                                                                 Networks nets) {
  for (torch::nn::Module* m : std::vector<torch::nn::Module*>{
           nets.vae ? nets.vae.get() : nullptr, nets.unet ? nets.unet.get() : nullptr,
           nets.controlnet ? nets.controlnet.get() : nullptr}) {
    if (m != nullptr) fd::model::SetRequiresGrad(*m, false);
  }
  fd::model::TrainableLora lora;
  if (has_lora_) {
    FD_ASSIGN_OR_RETURN(lora, fd::model::TrainableLiveLora(*nets.unet));
    for (torch::Tensor& t : lora.down) t.set_requires_grad(false);
    for (torch::Tensor& t : lora.up) t.set_requires_grad(false);
  }
  std::vector<std::vector<torch::Tensor>> groups;
  switch (stage) {
    case Stage::kVae:
      groups = {nets.vae->parameters()};
      break;
    case Stage::kDecoder: {
      // AutoencoderKL.decode's modules; the encoder and quant_conv, which
      // make the latents, stay frozen.
      std::vector<torch::Tensor> decoder = nets.vae->decoder->parameters();
      if (nets.vae->post_quant_conv) {
        for (const torch::Tensor& p : nets.vae->post_quant_conv->parameters()) {
          decoder.push_back(p);
        }
      }
      groups = {decoder};
      break;
    }
    case Stage::kBase:
      groups = {nets.unet->parameters()};
      break;
    case Stage::kControlNet:
      groups = {nets.controlnet->parameters()};
      if (options_.schedule[static_cast<int>(Stage::kControlNet)].unet_lr > 0) {
        groups.push_back(nets.unet->parameters());
      }
      break;
    case Stage::kControlLora:
      groups = {lora.down, lora.up};
      break;
    case Stage::kSelfConditioning:
      groups = {lora.down, lora.up, nets.controlnet->parameters()};
      break;
  }
  for (std::vector<torch::Tensor>& group : groups) {
    for (torch::Tensor& p : group) p.set_requires_grad(true);
  }
  return groups;
}

absl::Status Trainer::ConfigureStage(Stage stage) {
  if (stage == Stage::kDecoder && !options_.decoder_latents_from.empty() &&
      decoder_latents_.empty()) {
    FD_RETURN_IF_ERROR(GenerateDecoderLatents());
  }
  return TorchCall("ConfigureStage", [&]() -> absl::Status {
    FD_ASSIGN_OR_RETURN(std::vector<std::vector<torch::Tensor>> params,
                        TrainableGroups(stage, {vae_, unet_, controlnet_}));
    const StageSchedule& sched = options_.schedule[static_cast<int>(stage)];
    std::vector<torch::optim::OptimizerParamGroup> groups;
    group_lrs_.clear();
    trainable_.clear();
    for (size_t g = 0; g < params.size(); ++g) {
      // Groups lora_A, lora_B, ControlNet (train.py 2441-2482); stage 3's
      // ControlNet and stage 1's optional UNet have their own learning rates.
      const bool controlnet_group = stage == Stage::kSelfConditioning && g == 2;
      const bool unet_group = stage == Stage::kControlNet && g == 1;
      double lr = controlnet_group && sched.controlnet_lr > 0 ? sched.controlnet_lr : sched.lr;
      if (unet_group) lr = sched.unet_lr;
      trainable_.insert(trainable_.end(), params[g].begin(), params[g].end());
      auto options = std::make_unique<torch::optim::AdamWOptions>(lr);
      options->betas({0.9, 0.999}).eps(1e-8).weight_decay(options_.weight_decay);
      groups.emplace_back(params[g], std::move(options));
      group_lrs_.push_back(lr);
    }
    optimizer_ = std::make_unique<torch::optim::AdamW>(std::move(groups),
                                                       torch::optim::AdamWOptions(sched.lr));
    average_.reset();
    if (options_.ema_decay > 0) {
      average_ = std::make_unique<WeightAverage>(trainable_, options_.ema_decay);
    }
    // Data-parallel replicas: copies of every network, trained on their
    // share of each batch on their own thread; gradients are summed into
    // the masters and the masters' weights copied back after each step.
    replicas_.clear();
    Networks masters{vae_, unet_, controlnet_};
    for (int r = 1; r < options_.replicas; ++r) {
      Replica replica;
      if (vae_) {
        FD_ASSIGN_OR_RETURN(replica.nets.vae, fd::model::CopyVae(*vae_));
      }
      if (unet_) {
        FD_ASSIGN_OR_RETURN(replica.nets.unet, fd::model::CopyUNet(*unet_));
      }
      if (controlnet_) {
        FD_ASSIGN_OR_RETURN(replica.nets.controlnet, fd::model::CopyControlNet(*controlnet_));
      }
      FD_ASSIGN_OR_RETURN(std::vector<std::vector<torch::Tensor>> replica_params,
                          TrainableGroups(stage, replica.nets));
      for (const std::vector<torch::Tensor>& group : replica_params) {
        replica.trainable.insert(replica.trainable.end(), group.begin(), group.end());
      }
      if (replica.trainable.size() != trainable_.size()) {
        return absl::InternalError("a replica's trainable parameters differ from the master's");
      }
      replicas_.push_back(std::move(replica));
    }
    // After the copies: a copy is built from its config, without the flag.
    std::vector<Networks*> all_nets = {&masters};
    for (Replica& replica : replicas_) all_nets.push_back(&replica.nets);
    for (Networks* nets : all_nets) {
      if (nets->unet)
        fd::model::SetGradientCheckpointing(*nets->unet, options_.gradient_checkpointing);
      if (nets->controlnet) {
        fd::model::SetGradientCheckpointing(*nets->controlnet, options_.gradient_checkpointing);
      }
    }
    ResetLoader();
    return absl::OkStatus();
  });
}

void Trainer::ResetLoader() {
  loader_.reset();
  overfit_batch_.reset();
  BatchLoaderOptions options;
  options.threads = options_.loader_threads;
  options.prefetch = options_.prefetch;
  options.batch_size = options_.batch_size;
  options.seed = options_.seed;
  options.samples.stage = *stage_;
  options.samples.max_offset = options_.max_offset;
  options.samples.max_noise_sigma = options_.max_noise_sigma;
  options.samples.max_blur_sigma = options_.max_blur_sigma;
  options.samples.sky_injection = options_.sky_injection;
  options.samples.irradiance = options_.irradiance;
  options.samples.recolour_probability = options_.recolour_probability;
  options.samples.flip_probability = options_.flip_probability;
  if (options_.flip_plane_normal) options.samples.flip_plane_normal = *options_.flip_plane_normal;
  options.samples.generated_ratio = options_.selfcond_ratio;
  loader_ = std::make_unique<BatchLoader>(data_, pool_, options, step_ * options_.grad_accum);
}

torch::Tensor Trainer::EncodeLatents(fd::model::AutoencoderKLImpl& vae, const torch::Tensor& images,
                                     at::Generator& gen) {
  // vae.encode(x).latent_dist.sample() * scaling_factor, frozen VAE.
  torch::NoGradGuard no_grad;
  fd::model::LatentPosterior posterior = vae.encode(images);
  torch::Tensor noise = torch::randn(posterior.mean.sizes(), gen).to(posterior.mean.device());
  return posterior.Sample(noise) * vae.config().scaling_factor;
}

absl::StatusOr<torch::Tensor> Trainer::MicroStepLoss(const TrainingBatch& batch, int64_t micro_step,
                                                     int shard, Networks nets) {
  return TorchCall("training step", [&]() -> absl::StatusOr<torch::Tensor> {
    const Stage stage = *stage_;
    const uint64_t stream =
        MixSeed(options_.seed, static_cast<uint64_t>(stage), (1ULL << 61) + micro_step);
    at::Generator gen = at::make_generator<at::CPUGeneratorImpl>(
        shard == 0 ? stream : MixSeed(stream, static_cast<uint64_t>(shard), 0));
    fd::model::AutoencoderKLImpl& vae = *nets.vae;
    const torch::Device device = options_.device;
    AutocastScope autocast(device.is_cuda() && options_.dtype == torch::kBFloat16);
    const torch::Tensor x = batch.target.to(device);
    const int64_t b = x.size(0);
    if (stage == Stage::kVae) {
      torch::Tensor crops = x;
      const int64_t crop = options_.vae_crop;
      if (crop > 0 && (crop < x.size(2) || crop < x.size(3))) {
        // One random crop per frame, drawn from this micro-step's stream.
        std::vector<torch::Tensor> items;
        for (int64_t i = 0; i < b; ++i) {
          const int64_t top = torch::randint(0, x.size(2) - crop + 1, {1}, gen).item<int64_t>();
          const int64_t left = torch::randint(0, x.size(3) - crop + 1, {1}, gen).item<int64_t>();
          items.push_back(x[i].slice(1, top, top + crop).slice(2, left, left + crop));
        }
        crops = torch::stack(items);
      }
      fd::model::LatentPosterior posterior = vae.encode(crops);
      torch::Tensor z = posterior.Sample(torch::randn(posterior.mean.sizes(), gen).to(device));
      torch::Tensor reconstruction = vae.decode(z);
      torch::Tensor rec = torch::mse_loss(reconstruction, crops);
      // DiagonalGaussianDistribution.kl(): summed over latent elements,
      // averaged over the batch (LDM's kl_loss / batch size).
      torch::Tensor kl =
          0.5 * (posterior.mean.pow(2) + posterior.logvar.exp() - 1.0 - posterior.logvar)
                    .sum({1, 2, 3})
                    .mean();
      torch::Tensor loss = rec.to(torch::kFloat32) + options_.kl_weight * kl.to(torch::kFloat32);
      if (options_.colour_latent_scale > 0) {
        // The sample, not the mean: the tie also keeps those channels'
        // posterior noise small, so the denoiser sees the colour, not noise.
        loss = loss + torch::mse_loss(ColourLatents(z).to(torch::kFloat32),
                                      options_.colour_latent_scale *
                                          BlockColour(crops, vae.downsampling_factor()));
      }
      return loss;
    }
    if (stage == Stage::kDecoder) {
      // The decoder learns to map the frozen encoder's latents (a posterior
      // sample, what the diffusion stages train on) back to the frame. Whole
      // frames, not --vae_crop's crops: the decoder's GroupNorms and
      // mid-block attention then see the frame size they serve at
      // (docs/EVALUATION.md, "What changed in the eighth round").
      if (!decoder_latents_.empty()) {
        // --decoder_latents_from: the model's own latents of training
        // frames, drawn from this micro-step's stream (the loader's frames
        // are not used), each decoded towards its ground truth.
        const torch::Tensor picks = torch::randint(0, static_cast<int64_t>(decoder_latents_.size()),
                                                   {b}, gen, torch::kLong);
        std::vector<torch::Tensor> latents, frames;
        for (int64_t i = 0; i < b; ++i) {
          const DecoderLatent& d = decoder_latents_[static_cast<size_t>(picks[i].item<int64_t>())];
          latents.push_back(d.latent);
          frames.push_back(
              data_.sequences[static_cast<size_t>(d.sequence)].final_image[d.position]);
        }
        const torch::Tensor z = torch::stack(latents).to(device) / vae.config().scaling_factor;
        const torch::Tensor target = ToSigned(torch::stack(frames)).to(device);
        return torch::mse_loss(vae.decode(z), target).to(torch::kFloat32);
      }
      torch::Tensor z;
      {
        torch::NoGradGuard frozen;
        fd::model::LatentPosterior posterior = vae.encode(x);
        z = posterior.Sample(torch::randn(posterior.mean.sizes(), gen).to(device));
      }
      return torch::mse_loss(vae.decode(z), x).to(torch::kFloat32);
    }
    torch::Tensor latents = EncodeLatents(vae, x, gen);
    torch::Tensor noise = torch::randn(latents.sizes(), gen).to(device);
    torch::Tensor timesteps =
        SampleTimesteps(options_.timestep_sampling, alphas_cumprod_.size(0), b, gen);
    torch::Tensor acp = alphas_cumprod_.index_select(0, timesteps).to(device).view({b, 1, 1, 1});
    // DDPMScheduler.add_noise.
    torch::Tensor noisy = acp.sqrt() * latents + (1.0 - acp).sqrt() * noise;
    timesteps = timesteps.to(device);
    torch::Tensor embeds = prompt_embeds_.expand({b, -1, -1});
    std::vector<torch::Tensor> residuals;
    // The G-buffer condition, copied to the device once for the ControlNet
    // and the basecolor patches.
    const torch::Tensor cond = stage != Stage::kBase ? batch.condition.to(device) : torch::Tensor();
    if (stage != Stage::kBase) {
      if (stage == Stage::kControlLora) {
        torch::NoGradGuard frozen;  // stage 2: the ControlNet is frozen
        residuals = nets.controlnet->forward(noisy, timesteps, embeds, cond);
      } else {
        residuals = nets.controlnet->forward(noisy, timesteps, embeds, cond);
      }
    }
    torch::Tensor input = noisy;
    if (nets.unet->input_channels() != nets.unet->config().out_channels) {
      // UNet2DConditionModelEx: cat(noisy, previous-frame latent); before
      // stage 2 (a widened copy) the extra channels are zero.
      torch::Tensor previous = batch.previous.defined()
                                   ? EncodeLatents(vae, batch.previous.to(device), gen)
                                   : torch::zeros_like(noisy);
      input = torch::cat({noisy, previous}, 1);
      if (basecolor_patch_channels_ > 0) {
        FD_ASSIGN_OR_RETURN(torch::Tensor patches,
                            fd::model::BasecolorPatches(cond, vae.downsampling_factor()));
        input = torch::cat({input, patches}, 1);
      }
    }
    torch::Tensor prediction = nets.unet->forward(input, timesteps, embeds, residuals);
    // F.mse_loss(model_pred.float(), target.float()), the target by the
    // scheduler config's prediction_type (train.py).
    const torch::Tensor target = DiffusionTarget(prediction_type_, latents, noise, acp);
    torch::Tensor loss =
        torch::mse_loss(prediction.to(torch::kFloat32), target.to(torch::kFloat32));
    if (options_.pixel_loss_weight > 0) {
      // The frozen decoder's view of the implied clean latents: gradients
      // reach the denoiser through it, the VAE's weights stay as they are.
      const torch::Tensor clean = PredictedCleanLatents(prediction_type_, prediction, noisy, acp);
      const torch::Tensor decoded = vae.decode(clean / vae.config().scaling_factor);
      loss = loss + options_.pixel_loss_weight *
                        torch::mse_loss(decoded.to(torch::kFloat32), x.to(torch::kFloat32));
    }
    return loss;
  });
}

absl::StatusOr<double> Trainer::AccumulateMicroStep(const TrainingBatch& batch,
                                                    int64_t micro_step) {
  const double scale = 1.0 / static_cast<double>(options_.grad_accum);
  if (replicas_.empty()) {
    FD_ASSIGN_OR_RETURN(torch::Tensor loss,
                        MicroStepLoss(batch, micro_step, 0, {vae_, unet_, controlnet_}));
    (loss * scale).backward();
    return loss.item<double>();
  }
  // Shard k of the batch runs on replica k (k = 0: the masters, this thread);
  // each shard's loss is weighted by its share so that the summed gradients
  // are those of the batch mean.
  const int64_t b = batch.target.size(0);
  const int shards = static_cast<int>(std::min<int64_t>(b, 1 + replicas_.size()));
  auto shard_of = [&](int k) {
    const int64_t begin = b * k / shards, end = b * (k + 1) / shards;
    TrainingBatch part;
    part.target = batch.target.slice(0, begin, end);
    if (batch.previous.defined()) part.previous = batch.previous.slice(0, begin, end);
    if (batch.condition.defined()) part.condition = batch.condition.slice(0, begin, end);
    return std::make_pair(part, static_cast<double>(end - begin) / static_cast<double>(b));
  };
  auto run = [&](int k) -> absl::StatusOr<double> {
    const std::pair<TrainingBatch, double> shard = shard_of(k);
    const TrainingBatch& part = shard.first;
    const double share = shard.second;
    const Networks nets =
        k == 0 ? Networks{vae_, unet_, controlnet_} : replicas_[static_cast<size_t>(k - 1)].nets;
    FD_ASSIGN_OR_RETURN(torch::Tensor loss, MicroStepLoss(part, micro_step, k, nets));
    return TorchCall("replica backward", [&]() -> absl::StatusOr<double> {
      (loss * (share * scale)).backward();
      return loss.item<double>() * share;
    });
  };
  std::vector<std::future<absl::StatusOr<double>>> others;
  for (int k = 1; k < shards; ++k) {
    others.push_back(std::async(std::launch::async, [&run, k]() {
      // One intra-op thread per replica: the parallelism is the replicas'.
      at::set_num_threads(1);
      return run(k);
    }));
  }
  absl::StatusOr<double> total = run(0);
  for (auto& other : others) {
    absl::StatusOr<double> loss = other.get();
    if (total.ok() && !loss.ok()) total = loss.status();
    if (total.ok()) total = *total + *loss;
  }
  return total;
}

absl::StatusOr<double> Trainer::TrainStep() {
  if (!stage_) return absl::FailedPreconditionError("TrainStep outside a stage");
  const auto start = std::chrono::steady_clock::now();
  const double wait_before = loader_->wait_seconds();
  double loss_sum = 0;
  FD_RETURN_IF_ERROR(TorchCall("TrainStep", [&]() -> absl::Status {
    optimizer_->zero_grad();
    for (Replica& replica : replicas_) {
      for (torch::Tensor& p : replica.trainable) {
        if (p.grad().defined()) p.mutable_grad().zero_();
      }
    }
    for (int a = 0; a < options_.grad_accum; ++a) {
      if (!options_.overfit_one_batch || !overfit_batch_) {
        FD_ASSIGN_OR_RETURN(TrainingBatch batch, loader_->Next());
        overfit_batch_ = std::make_unique<TrainingBatch>(std::move(batch));
      }
      // --overfit_one_batch: micro-step 0's batch, noise and timesteps again.
      const int64_t micro_step = options_.overfit_one_batch ? 0 : step_ * options_.grad_accum + a;
      FD_ASSIGN_OR_RETURN(double loss, AccumulateMicroStep(*overfit_batch_, micro_step));
      loss_sum += loss;
    }
    {
      torch::NoGradGuard no_grad;
      for (Replica& replica : replicas_) {
        for (size_t i = 0; i < trainable_.size(); ++i) {
          const torch::Tensor& g = replica.trainable[i].grad();
          if (!g.defined()) continue;
          if (trainable_[i].grad().defined()) {
            trainable_[i].mutable_grad().add_(g);
          } else {
            trainable_[i].mutable_grad() = g.clone();
          }
        }
      }
    }
    torch::nn::utils::clip_grad_norm_(trainable_, options_.max_grad_norm);
    const double factor = CosineWithWarmup(step_, schedule().warmup, schedule().steps);
    for (size_t g = 0; g < optimizer_->param_groups().size(); ++g) {
      optimizer_->param_groups()[g].options().set_lr(group_lrs_[g] * factor);
    }
    optimizer_->step();
    if (average_) average_->Update(step_ + 1);
    torch::NoGradGuard no_grad;
    for (Replica& replica : replicas_) {
      for (size_t i = 0; i < trainable_.size(); ++i) replica.trainable[i].copy_(trainable_[i]);
    }
    return absl::OkStatus();
  }));
  ++step_;
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  step_seconds_ += seconds;
  wait_seconds_ += loader_->wait_seconds() - wait_before;
  const double loss = loss_sum / options_.grad_accum;
  log_->Step({*stage_, step_, schedule().steps, loss,
              group_lrs_[0] * CosineWithWarmup(step_ - 1, schedule().warmup, schedule().steps),
              seconds, loader_wait_fraction()});
  return loss;
}

absl::Status Trainer::GenerateDecoderLatents() {
  const auto start = std::chrono::steady_clock::now();
  fd::model::EnvironmentOptions env_options;
  env_options.device = options_.device;
  FD_ASSIGN_OR_RETURN(std::shared_ptr<fd::model::Environment> env,
                      fd::model::LoadEnvironment(options_.decoder_latents_from, env_options));
  // Its latents mean what this VAE's encoder makes of a frame only if the
  // encoder is the same (up to the float16 export's rounding).
  FD_RETURN_IF_ERROR(TorchCall("compare encoders", [&]() -> absl::Status {
    const auto theirs = env->vae->named_parameters();
    bool same = std::abs(env->vae->config().scaling_factor - vae_->config().scaling_factor) <=
                1e-6 * std::abs(vae_->config().scaling_factor);
    for (const auto& p : vae_->named_parameters()) {
      if (!absl::StartsWith(p.key(), "encoder.") && !absl::StartsWith(p.key(), "quant_conv.")) {
        continue;
      }
      const torch::Tensor* other = theirs.find(p.key());
      same = same && other != nullptr && other->sizes() == p.value().sizes() &&
             torch::allclose(other->to(torch::kFloat32), p.value().detach().to(other->device()),
                             /*rtol=*/1e-3, /*atol=*/1e-4);
    }
    if (!same) {
      return absl::FailedPreconditionError(
          absl::StrCat("--decoder_latents_from ", options_.decoder_latents_from,
                       ": its VAE encoder is not the one being fine-tuned (give --vae ",
                       options_.decoder_latents_from, ")"));
    }
    return absl::OkStatus();
  }));
  DecoderLatentOptions latent_options;
  latent_options.chains = options_.decoder_chains;
  latent_options.chain_frames = options_.decoder_chain_frames;
  latent_options.seed = options_.seed;
  FD_ASSIGN_OR_RETURN(DecoderLatentSet rendered,
                      fd::trainer::RenderDecoderLatents(env, data_, latent_options));
  decoder_latents_ = std::move(rendered.latents);
  decoder_latents_psnr_ = rendered.mean_psnr;
  log_->Event("decoder_latents",
              {{"from", options_.decoder_latents_from},
               {"latents", decoder_latents_.size()},
               {"chains", options_.decoder_chains},
               {"chain_frames", options_.decoder_chain_frames},
               {"mean_psnr", rendered.mean_psnr},
               {"seconds",
                std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count()}});
  return absl::OkStatus();
}

bool Trainer::FromVaeDir(Stage stage) const {
  return !options_.vae_dir.empty() && (stage == Stage::kVae || vae_sources_.count(stage) > 0);
}

absl::Status Trainer::LoadTrainedVae() {
  // An environment folder holds its autoencoder in vae/; a VAE folder is
  // config.json + weights.
  fs::path dir(options_.vae_dir);
  if (PathExists((dir / "vae" / "config.json").string())) dir /= "vae";
  if (!PathExists((dir / "config.json").string())) {
    return absl::NotFoundError(
        absl::StrCat("--vae ", options_.vae_dir, " has no config.json (nor vae/config.json)"));
  }
  FD_ASSIGN_OR_RETURN(vae_json_, ReadTextFile((dir / "config.json").string()));
  FD_ASSIGN_OR_RETURN(vae_, fd::model::LoadVae(dir.string(), options_.device, torch::kFloat32));
  // The UNet's latent follows the autoencoder's.
  nlohmann::json unet = nlohmann::json::parse(unet_json_);
  unet["in_channels"] = vae_->config().latent_channels;
  unet["out_channels"] = vae_->config().latent_channels;
  unet_json_ = unet.dump(2) + "\n";
  completed_[static_cast<int>(Stage::kVae)] = true;
  // An environment trained here says how its VAE was trained; the record
  // of this run keeps that (its stage0-vae entry and commands).
  const fs::path record = fs::path(options_.vae_dir) / "environment.json";
  if (PathExists(record.string())) {
    FD_ASSIGN_OR_RETURN(std::string text, ReadTextFile(record.string()));
    const nlohmann::json env = nlohmann::json::parse(text, nullptr, /*allow_exceptions=*/false);
    const nlohmann::json training =
        env.is_object() ? env.value("training", nlohmann::json::object()) : nlohmann::json();
    if (training.is_object()) {
      for (const nlohmann::json& stage : training.value("stages", nlohmann::json::array())) {
        for (Stage kept : {Stage::kVae, Stage::kDecoder}) {
          if (!stage.is_object() || !stage.contains("stage") || stage["stage"] != StageName(kept)) {
            continue;
          }
          // When that environment kept an autoencoder from another one in
          // turn, its entry already names the commands that trained it;
          // its own commands would only say "--vae".
          vae_sources_[kept] = {
              {"stage", stage},
              {"commands", stage.contains("from_commands")
                               ? stage["from_commands"]
                               : training.value("commands", nlohmann::json::array())}};
          if (kept == Stage::kDecoder && !options_.decoder_latents_from.empty()) {
            // This run fine-tunes that decoder again, on the model's own
            // latents; its record keeps the fine-tune it follows.
            previous_decoder_ = vae_sources_[kept];
            vae_sources_.erase(kept);
            continue;
          }
          // Done in that environment, so done here: stage 0a always, the
          // decoder fine-tune when it had one.
          completed_[static_cast<int>(kept)] = true;
        }
      }
    }
  }
  FD_RETURN_IF_ERROR(MeasureVaePsnr());
  return absl::OkStatus();
}

absl::Status Trainer::FinishVae() {
  // LDM scale_by_std: scaling_factor = 1 / std(z) of the encoded frames
  // (here up to 256 training frames, mean + std * noise, seeded).
  FD_RETURN_IF_ERROR(TorchCall("vae scaling factor", [&]() -> absl::Status {
    torch::NoGradGuard no_grad;
    at::Generator gen = at::make_generator<at::CPUGeneratorImpl>(options_.seed + 17);
    std::vector<torch::Tensor> latents;
    int64_t taken = 0;
    for (const TrainingSequence& seq : data_.sequences) {
      for (int64_t i = 0; i < seq.size() && taken < 256; i += 8, taken += 8) {
        torch::Tensor x = ToSigned(seq.final_image.slice(0, i, std::min(i + 8, seq.size())));
        fd::model::LatentPosterior p = vae_->encode(x.to(options_.device));
        latents.push_back(p.Sample(torch::randn(p.mean.sizes(), gen).to(options_.device)));
      }
    }
    const double scale = 1.0 / torch::cat(latents).std().item<double>();
    nlohmann::json j = nlohmann::json::parse(vae_json_);
    j["scaling_factor"] = scale;
    vae_json_ = j.dump(2) + "\n";
    FD_ASSIGN_OR_RETURN(fd::model::AutoencoderKLConfig config,
                        fd::model::ParseAutoencoderKLConfig(vae_json_, "vae config"));
    FD_ASSIGN_OR_RETURN(fd::model::AutoencoderKL rescaled, fd::model::MakeVae(config));
    rescaled->to(options_.device);
    std::map<std::string, torch::Tensor> state;
    for (const auto& item : vae_->named_parameters()) state[item.key()] = item.value().detach();
    FD_RETURN_IF_ERROR(fd::model::LoadStateDict(*rescaled, state));
    vae_ = rescaled;
    return absl::OkStatus();
  }));
  return MeasureVaePsnr();
}

absl::Status Trainer::MeasureVaePsnr() {
  // Reconstruction PSNR on held-out frames (the validation sequences, else
  // the training frames, said so in the log).
  const TrainingData& held_out = validation_data_.sequences.empty() ? data_ : validation_data_;
  double mse_sum = 0;
  int64_t frames = 0;
  FD_RETURN_IF_ERROR(TorchCall("vae psnr", [&]() -> absl::Status {
    torch::NoGradGuard no_grad;
    for (const TrainingSequence& seq : held_out.sequences) {
      for (int64_t i = 0; i < seq.size() && frames < 64; i += 4) {
        torch::Tensor x =
            ToSigned(seq.final_image.slice(0, i, std::min(i + 4, seq.size()))).to(options_.device);
        torch::Tensor rec = vae_->decode(vae_->encode(x).mean).clamp(-1, 1);
        // PSNR on [0, 1] images, per frame.
        torch::Tensor mse = ((rec - x) / 2).pow(2).mean({1, 2, 3});
        mse_sum += (-10.0 * torch::log10(mse.clamp_min(1e-12))).sum().item<double>();
        frames += x.size(0);
      }
    }
    return absl::OkStatus();
  }));
  vae_psnr_ = frames > 0 ? mse_sum / frames : 0;
  log_->Event("vae", {{"scaling_factor", vae_->config().scaling_factor},
                      {"reconstruction_psnr", vae_psnr_},
                      {"psnr_frames", frames},
                      {"held_out", !validation_data_.sequences.empty()}});
  return absl::OkStatus();
}

double Trainer::StageWallSeconds() const {
  if (!stage_) return 0;
  return stage_seconds_before_ +
         std::chrono::duration<double>(std::chrono::steady_clock::now() - stage_clock_).count();
}

absl::Status Trainer::EndStage() {
  if (!stage_) return absl::FailedPreconditionError("EndStage outside a stage");
  const Stage stage = *stage_;
  // The average replaces the last weights before anything reads them (the
  // VAE's scaling factor, the export, the validation, the next stage).
  if (average_) {
    FD_RETURN_IF_ERROR(TorchCall("weight average", [&]() -> absl::Status {
      average_->Swap();
      return absl::OkStatus();
    }));
  }
  if (stage == Stage::kVae) FD_RETURN_IF_ERROR(FinishVae());
  // The encoder did not change, so neither does the scaling factor the
  // diffusion stages were trained with; only the reconstruction does.
  if (stage == Stage::kDecoder) FD_RETURN_IF_ERROR(MeasureVaePsnr());
  stage_seconds_[static_cast<int>(stage)] = StageWallSeconds();
  stage_settings_[static_cast<int>(stage)] = StageSettings(stage);
  loader_.reset();
  optimizer_.reset();
  trainable_.clear();
  replicas_.clear();
  std::unique_ptr<WeightAverage> average = std::move(average_);
  completed_[static_cast<int>(stage)] = true;
  stage_.reset();
  last_stage_ = StageName(stage);
  log_->Event("stage_end", {{"stage", StageName(stage)},
                            {"steps", step_},
                            {"loss_ema", log_->loss_ema()},
                            {"seconds", step_seconds_},
                            {"wall_seconds", stage_seconds_[static_cast<int>(stage)]},
                            {"loader_wait_fraction", loader_wait_fraction()}});
  FD_RETURN_IF_ERROR(log_->WriteLossCurve(stage));
  FD_RETURN_IF_ERROR(SaveCheckpoint());
  FD_RETURN_IF_ERROR(ExportEnvironment());
  if (average && controlnet_) {
    // The last weights, servable, for comparing them with the average.
    const std::string last =
        (fs::path(options_.out_dir) / "train" / absl::StrCat("last-", StageName(stage))).string();
    FD_RETURN_IF_ERROR(TorchCall("weight average", [&]() -> absl::Status {
      average->Swap();
      absl::Status written = WriteModelParts(last, options_.export_dtype);
      average->Swap();
      return written;
    }));
    log_->Event("export", {{"dir", last}, {"weights", "last"}});
  }
  if (controlnet_) FD_RETURN_IF_ERROR(Validate().status());
  return absl::OkStatus();
}

absl::StatusOr<std::shared_ptr<fd::model::Environment>> Trainer::EnvironmentView(
    SchedulerType scheduler, int steps) {
  if (!unet_ || !controlnet_ || !vae_) {
    return absl::FailedPreconditionError("no ControlNet yet: the pipeline needs stage 1");
  }
  auto env = std::make_shared<fd::model::Environment>();
  env->dir = options_.out_dir;
  env->settings.name = fs::path(options_.out_dir).filename().string();
  env->settings.prompt = options_.prompt;
  env->settings.width = options_.width;
  env->settings.height = options_.height;
  env->settings.steps = steps;
  env->settings.scheduler = scheduler;
  env->settings.sky_mode = fd::model::SkyFillMode::kSkyImage;
  // Stage 1 trains on black irradiance, and so does --no-irradiance.
  env->settings.irradiance_from_previous = options_.irradiance && has_lora_;
  env->device = options_.device;
  env->dtype = torch::kFloat32;
  env->vae = vae_;
  env->controlnet = controlnet_;
  env->lora_mode = fd::model::LoraMode::kLive;
  if (unet_->input_channels() == unet_->config().out_channels) {
    // Before stage 2 the server pads conv_in with zeros; so does the view.
    FD_ASSIGN_OR_RETURN(env->unet, fd::model::WidenConvIn(*unet_, basecolor_patch_channels_));
  } else {
    env->unet = unet_;
  }
  FD_ASSIGN_OR_RETURN(env->schedulers,
                      fd::model::BuildSchedulers(scheduler_json_, scheduler, "scheduler config"));
  env->prompt_embeds = prompt_embeds_;
  return env;
}

absl::Status Trainer::GeneratePool() {
  if (!stage_ || *stage_ != Stage::kSelfConditioning) {
    return absl::FailedPreconditionError("GeneratePool outside stage 3");
  }
  const auto start = std::chrono::steady_clock::now();
  FD_ASSIGN_OR_RETURN(std::shared_ptr<fd::model::Environment> env,
                      EnvironmentView(SchedulerType::kDPMSolverMultistep, options_.selfcond_steps));
  SampleRandom rng(MixSeed(options_.seed, static_cast<uint64_t>(Stage::kSelfConditioning),
                           (1ULL << 60) + static_cast<uint64_t>(step_)));
  const int64_t frames = data_.frame_count();
  // Default: as many frames as the authors' rounds give each training
  // sample (500 per 2000 steps x 8 samples: each frame is used ~16 times).
  const int64_t samples_per_round = SelfcondEvery() * options_.batch_size * options_.grad_accum;
  const int64_t default_count = std::clamp<int64_t>((samples_per_round + 31) / 32, 4, 500);
  const int count = static_cast<int>(std::min<int64_t>(
      options_.selfcond_count > 0 ? options_.selfcond_count : default_count, frames));
  struct Job {
    int sequence;
    int64_t position, previous_position;
    torch::Tensor previous;
    int depth;
  };
  std::vector<Job> jobs;
  std::set<std::pair<int, int64_t>> chosen;
  // Chained part: the next frame of a frame the last round generated, from
  // that generated frame (GBufferDataset generate_conditioning_images).
  std::vector<Job> chained;
  for (const GeneratedFrame& g : pool_) {
    const TrainingSequence& seq = data_.sequences[static_cast<size_t>(g.sequence)];
    for (int64_t next : {g.position + 1, g.position + 2}) {
      if (next >= seq.size()) continue;
      if (chosen.insert({g.sequence, next}).second) {
        chained.push_back({g.sequence, next, g.position, g.image, g.chain_depth + 1});
      }
      break;
    }
  }
  std::shuffle(chained.begin(), chained.end(), rng.engine);
  const size_t chained_count =
      std::min(chained.size(), static_cast<size_t>(count * options_.selfcond_chain_ratio));
  chosen.clear();
  for (size_t i = 0; i < chained_count; ++i) {
    chosen.insert({chained[i].sequence, chained[i].position});
    jobs.push_back(chained[i]);
  }
  // Fresh part: random frames from a ground-truth previous frame at a
  // sampled offset. (The authors' code adds noise to this part's irradiance
  // only, as a side effect of a worker-process cache, training-reference
  // §3.2; here both paths see the clean frame.)
  for (int attempts = 0; static_cast<int>(jobs.size()) < count && attempts < 20 * count;
       ++attempts) {
    int64_t flat = static_cast<int64_t>(rng.engine() % static_cast<uint64_t>(frames));
    size_t s = 0;
    while (flat >= data_.sequences[s].size()) flat -= data_.sequences[s++].size();
    if (!chosen.insert({static_cast<int>(s), flat}).second) continue;
    const TrainingSequence& seq = data_.sequences[s];
    const int delta = SampleTemporalOffset(flat, seq.size(), options_.max_offset, rng);
    jobs.push_back({static_cast<int>(s), flat, flat + delta, seq.final_image[flat + delta], 1});
  }
  std::vector<GeneratedFrame> pool;
  fd::model::FramePipeline pipeline(env);
  constexpr size_t kBatch = 4;  // --generated_conditioning_batch_size
  for (size_t first = 0; first < jobs.size(); first += kBatch) {
    std::vector<fd::model::PipelineInput> requests;
    std::vector<uint64_t> seeds;
    for (size_t i = first; i < std::min(jobs.size(), first + kBatch); ++i) {
      const Job& job = jobs[i];
      seeds.push_back(MixSeed(options_.seed, static_cast<uint64_t>(step_), i));
      requests.push_back(
          MakeFrameRequest({&data_.sequences[static_cast<size_t>(job.sequence)], job.position,
                            job.previous, job.previous_position, seeds.back()}));
    }
    FD_ASSIGN_OR_RETURN(std::vector<fd::model::FrameOutput> outputs, pipeline.Render(requests));
    for (size_t i = 0; i < outputs.size(); ++i) {
      const Job& job = jobs[first + i];
      pool.push_back({job.sequence, job.position,
                      outputs[i].image_uint8.permute({2, 0, 1}).contiguous().clone(), job.depth,
                      job.previous_position, seeds[i]});
    }
  }
  pool_ = std::move(pool);
  pool_step_ = step_;
  ResetLoader();
  int max_depth = 0;
  for (const GeneratedFrame& g : pool_) max_depth = std::max(max_depth, g.chain_depth);
  log_->Event("selfcond_round",
              {{"step", step_},
               {"frames", pool_.size()},
               {"chained", chained_count},
               {"max_chain_depth", max_depth},
               {"seconds",
                std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count()}});
  return absl::OkStatus();
}

absl::StatusOr<ValidationResult> Trainer::Validate() {
  const TrainingData& held_out = validation_data_.sequences.empty() ? data_ : validation_data_;
  FD_ASSIGN_OR_RETURN(std::shared_ptr<fd::model::Environment> env, EnvironmentView());
  FD_ASSIGN_OR_RETURN(ValidationResult result, RenderValidation(env, held_out.sequences.front(),
                                                                options_.validation_frames));
  const std::string stage = stage_ ? StageName(*stage_) : last_stage_;
  const std::string sheet = (fs::path(options_.out_dir) / "train" /
                             absl::StrCat("validation-", stage, "-", step_, ".png"))
                                .string();
  FD_RETURN_IF_ERROR(fd::client::WritePng(sheet, result.contact_sheet));
  nlohmann::json psnr = nlohmann::json::array(), ssim = nlohmann::json::array();
  for (const ValidationFrame& f : result.frames) {
    psnr.push_back(f.psnr);
    ssim.push_back(f.ssim);
  }
  log_->Event("validation", {{"stage", stage},
                             {"step", step_},
                             {"held_out", !validation_data_.sequences.empty()},
                             {"mean_psnr", result.mean_psnr},
                             {"mean_ssim", result.mean_ssim},
                             {"psnr", psnr},
                             {"ssim", ssim},
                             {"contact_sheet", sheet}});
  return result;
}

}  // namespace fd::trainer

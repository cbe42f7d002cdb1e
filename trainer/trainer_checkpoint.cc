// Checkpoints (written atomically, loaded for --resume and for later stages)
// and the export of the servable environment; see trainer.h for the layout.
#include <torch/torch.h>
#include <unistd.h>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "base/status_macros.h"
#include "model/checkpoint/checkpoint_writer.h"
#include "model/checkpoint/safetensors.h"
#include "model/lora/apply_lora.h"
#include "model/lora/lora_file.h"
#include "model/runtime/torch_call.h"
#include "model/text/clip_text_model.h"
#include "trainer/file_io.h"
#include "trainer/trainer.h"

namespace fd::trainer {
namespace {

namespace fs = std::filesystem;
using Json = nlohmann::json;

constexpr char kStateFile[] = "trainer_state.json";
constexpr char kOptimizerFile[] = "optimizer.pt";
constexpr char kPoolFile[] = "selfcond_pool.safetensors";
constexpr char kAverageFile[] = "weight_average.safetensors";

// fsync of a file written by another library (torch::save).
absl::Status SyncFile(const std::string& path) {
  std::FILE* f = std::fopen(path.c_str(), "rb+");
  if (f == nullptr) return absl::InternalError(absl::StrCat("cannot open ", path));
  const bool ok = ::fsync(::fileno(f)) == 0;
  std::fclose(f);
  return ok ? absl::OkStatus() : absl::InternalError(absl::StrCat("cannot sync ", path));
}

constexpr char kStage1UnetLrKey[] = "stage1_unet_lr";

// What a checkpoint must agree on with the options of the run resuming it.
Json Fingerprint(const TrainerOptions& o, int64_t lora_rank) {
  Json j = {{"preset", o.preset},
            {"width", o.width},
            {"height", o.height},
            {"seed", o.seed},
            {"batch_size", o.batch_size},
            {"grad_accum", o.grad_accum},
            {"lora_rank", lora_rank},
            {"base", o.base_dir},
            {"sky_injection", o.sky_injection},
            {"latent_channels", o.latent_channels},
            {"vae_crop", o.vae_crop}};
  // Only when set, so that checkpoints written before the flag still resume;
  // it changes the optimizer's groups.
  const double unet_lr = o.schedule[static_cast<int>(Stage::kControlNet)].unet_lr;
  if (unet_lr > 0) j[kStage1UnetLrKey] = unet_lr;
  if (!o.vae_dir.empty()) j["vae"] = o.vae_dir;
  if (o.colour_latent_scale > 0) j["colour_latent_scale"] = o.colour_latent_scale;
  if (!o.decoder_latents_from.empty()) {
    j["decoder_latents_from"] = o.decoder_latents_from;
    j["decoder_chains"] = o.decoder_chains;
    j["decoder_chain_frames"] = o.decoder_chain_frames;
  }
  if (!o.prediction_type.empty() && o.prediction_type != "epsilon") {
    j["prediction_type"] = o.prediction_type;
  }
  return j;
}

std::string EnvironmentJson(const TrainerOptions& o, const std::array<bool, kStageCount>& done,
                            bool has_lora, const Json& training) {
  std::string stages;
  for (int s = 0; s < kStageCount; ++s) {
    if (done[s])
      absl::StrAppend(&stages, stages.empty() ? "" : ", ", StageName(static_cast<Stage>(s)));
  }
  Json j = {{"name", fs::path(o.out_dir).filename().string()},
            {"description", absl::StrCat("Trained by framediffuser-train (", stages, ") on ",
                                         o.width, "x", o.height, " frames of ",
                                         absl::StrJoin(o.data_dirs, ", "), ", preset ", o.preset)},
            {"prompt", o.prompt},
            {"width", o.width},
            {"height", o.height},
            {"steps", o.inference_steps},
            {"scheduler", "unipc"},
            // The model learned sky pixels filled from the frame's ground
            // truth (sky injection): clients send a sky image, or
            // --sky_mode previous_output fills them from the last frame.
            {"sky_mode", !o.sky_mode.empty() ? o.sky_mode
                         : o.sky_injection   ? "sky_image"
                                             : "none"},
            {"training", training}};
  // Stage 1 alone (the X->RGB baseline) has no ControlLoRA and saw black
  // irradiance; --no-irradiance keeps it black in every stage.
  if (!has_lora) j["controllora"] = false;
  if (!has_lora || !o.irradiance) j["irradiance"] = "black";
  return j.dump(2) + "\n";
}

}  // namespace

absl::Status Trainer::WriteModelParts(const std::string& dir, torch::Dtype dtype) {
  const fs::path out(dir);
  FD_RETURN_IF_ERROR(fd::model::CreateDirectories(dir));
  if (vae_) {
    FD_RETURN_IF_ERROR(
        fd::model::WriteModelFolder(*vae_, vae_json_, (out / "vae").string(), dtype));
  }
  if (unet_) {
    FD_RETURN_IF_ERROR(
        fd::model::WriteModelFolder(*unet_, unet_json_, (out / "unet").string(), dtype));
  }
  if (controlnet_) {
    FD_RETURN_IF_ERROR(fd::model::WriteModelFolder(*controlnet_, controlnet_json_,
                                                   (out / "controlnet").string(), dtype));
  }
  if (has_lora_) {
    FD_ASSIGN_OR_RETURN(auto lora, fd::model::LiveLoraStateDict(*unet_, dtype));
    FD_RETURN_IF_ERROR(fd::model::CreateDirectories((out / "controllora").string()));
    FD_RETURN_IF_ERROR(fd::model::WriteSafetensorsFile(
        (out / "controllora" / "pytorch_lora_weights.safetensors").string(), lora));
  }
  if (prompt_embeds_.defined()) {
    FD_RETURN_IF_ERROR(fd::model::WriteSafetensorsFile(
        (out / "prompt_embeds.safetensors").string(),
        {{"prompt_embeds", prompt_embeds_.detach().to(torch::kCPU, dtype)}}));
  }
  FD_RETURN_IF_ERROR(fd::model::CreateDirectories((out / "scheduler").string()));
  FD_RETURN_IF_ERROR(fd::model::WriteFileAtomically(
      (out / "scheduler" / "scheduler_config.json").string(), scheduler_json_));
  return fd::model::WriteFileAtomically(
      (out / "environment.json").string(),
      EnvironmentJson(options_, completed_, has_lora_, TrainingRecord()));
}

Json Trainer::StageSettings(Stage stage) const {
  const StageSchedule& sched = options_.schedule[static_cast<int>(stage)];
  Json j = {{"steps", sched.steps}, {"lr", sched.lr}};
  if (stage == Stage::kControlNet && sched.unet_lr > 0) j["unet_lr"] = sched.unet_lr;
  if (stage == Stage::kSelfConditioning && sched.controlnet_lr > 0) {
    j["controlnet_lr"] = sched.controlnet_lr;
  }
  if (stage == Stage::kVae && options_.colour_latent_scale > 0) {
    j["colour_latent_scale"] = options_.colour_latent_scale;
  }
  if (stage == Stage::kDecoder && !options_.decoder_latents_from.empty()) {
    j["latents_from"] = options_.decoder_latents_from;
    j["chains"] = options_.decoder_chains;
    j["chain_frames"] = options_.decoder_chain_frames;
    if (decoder_latents_psnr_ > 0) j["latents_psnr_db"] = decoder_latents_psnr_;
    if (previous_decoder_.is_object()) {
      // The fine-tune on the encoder's latents that this one follows.
      Json follows = previous_decoder_.at("stage");
      follows["from"] = options_.vae_dir;
      follows["from_commands"] = previous_decoder_.at("commands");
      j["follows"] = follows;
    }
  }
  if (stage != Stage::kVae && stage != Stage::kDecoder) {
    j["timestep_sampling"] =
        options_.timestep_sampling == TimestepSampling::kCubic ? "cubic" : "uniform";
    if (options_.pixel_loss_weight > 0) j["pixel_loss_weight"] = options_.pixel_loss_weight;
  }
  if (options_.ema_decay > 0) j["ema_decay"] = options_.ema_decay;
  if ((stage == Stage::kControlLora || stage == Stage::kSelfConditioning) &&
      options_.max_blur_sigma > 0) {
    j["previous_blur_max_sigma"] = options_.max_blur_sigma;
  }
  if (stage != Stage::kVae && stage != Stage::kDecoder && stage != Stage::kBase &&
      options_.flip_probability > 0) {
    j["flip_probability"] = options_.flip_probability;
    j["flip_plane_normal"] = *options_.flip_plane_normal;
  }
  return j;
}

// What the environment was trained on and how: environment.json's
// "training" (the README's retraining command reproduces it).
Json Trainer::TrainingRecord() const {
  Json stages = Json::array();
  for (int s = 0; s < kStageCount; ++s) {
    if (!completed_[s]) continue;
    const Stage stage = static_cast<Stage>(s);
    const bool from_base =
        !options_.base_dir.empty() && (stage == Stage::kVae || stage == Stage::kBase);
    const bool from_vae = FromVaeDir(stage);
    Json entry = {{"stage", StageName(stage)}};
    if (from_base || from_vae) {
      entry["from"] = from_base ? options_.base_dir : options_.vae_dir;
      if (auto source = vae_sources_.find(stage); from_vae && source != vae_sources_.end()) {
        // How that autoencoder was trained, from its environment's record.
        for (const auto& [key, value] : source->second.at("stage").items()) {
          if (key != "stage" && key != "from") entry[key] = value;  // "from": this run's
        }
        entry["from_commands"] = source->second.at("commands");
      }
    } else {
      // A stage finished before its settings were persisted (older
      // checkpoints) falls back to this run's flags.
      const Json& settings =
          stage_settings_[s].is_object() ? stage_settings_[s] : StageSettings(stage);
      entry.update(settings);
      if (!stage_settings_[s].is_object()) entry.erase("timestep_sampling");  // not known
      entry["seconds"] = stage_seconds_[s];
    }
    stages.push_back(entry);
  }
  Json record = {{"trainer", "framediffuser-train"},
                 {"commands", commands_},
                 {"data", options_.data_dirs},
                 {"validation", options_.validation_dirs},
                 {"frames", data_.frame_count()},
                 {"preset", options_.preset},
                 {"latent_channels", vae_ ? vae_->config().latent_channels : 0},
                 {"resolution", absl::StrCat(options_.width, "x", options_.height)},
                 {"seed", options_.seed},
                 {"batch_size", options_.batch_size},
                 {"device", options_.device.str()},
                 {"replicas", options_.replicas},
                 {"noise_injection_max_sigma", options_.max_noise_sigma},
                 {"irradiance", options_.irradiance},
                 {"recolour_probability", options_.recolour_probability},
                 {"prediction_type", prediction_type_},
                 {"stages", stages}};
  if (vae_psnr_ > 0) {
    record["vae_reconstruction_psnr_db"] = vae_psnr_;
    record["vae_reconstruction_psnr_on"] =
        options_.validation_dirs.empty() ? "training frames" : "held-out frames";
  }
  return record;
}

absl::Status Trainer::ExportEnvironment() {
  FD_RETURN_IF_ERROR(WriteModelParts(options_.out_dir, options_.export_dtype));
  log_->Event("export", {{"dir", options_.out_dir}});
  return absl::OkStatus();
}

absl::Status Trainer::SaveCheckpoint() {
  const fs::path root = fs::path(options_.out_dir) / "checkpoints";
  const std::string stage = stage_ ? StageName(*stage_) : last_stage_ + "-end";
  const std::string name = absl::StrFormat("%06d-%s-step%d", ++checkpoint_counter_, stage, step_);
  const fs::path tmp = root / absl::StrCat(".tmp-", name);
  std::error_code ec;
  fs::remove_all(tmp, ec);
  FD_RETURN_IF_ERROR(WriteModelParts(tmp.string(), torch::kFloat32));
  if (optimizer_) {
    const std::string path = (tmp / kOptimizerFile).string();
    FD_RETURN_IF_ERROR(fd::model::TorchCall("save optimizer", [&]() -> absl::Status {
      torch::save(*optimizer_, path);
      return absl::OkStatus();
    }));
    FD_RETURN_IF_ERROR(SyncFile(path));
  }
  if (average_) {
    FD_RETURN_IF_ERROR(
        fd::model::WriteSafetensorsFile((tmp / kAverageFile).string(), average_->State()));
  }
  if (!pool_.empty()) {
    std::map<std::string, torch::Tensor> tensors;
    std::vector<torch::Tensor> images;
    torch::Tensor info = torch::empty({static_cast<int64_t>(pool_.size()), 5}, torch::kLong);
    for (size_t i = 0; i < pool_.size(); ++i) {
      images.push_back(pool_[i].image);
      const int64_t row = static_cast<int64_t>(i);
      info[row][0] = pool_[i].sequence;
      info[row][1] = pool_[i].position;
      info[row][2] = pool_[i].chain_depth;
      info[row][3] = pool_[i].previous_position;
      info[row][4] = static_cast<int64_t>(pool_[i].seed);
    }
    tensors["images"] = torch::stack(images);
    tensors["info"] = info;
    FD_RETURN_IF_ERROR(fd::model::WriteSafetensorsFile((tmp / kPoolFile).string(), tensors));
  }
  Json completed = Json::array();
  for (int s = 0; s < kStageCount; ++s) {
    if (completed_[s]) completed.push_back(StageName(static_cast<Stage>(s)));
  }
  Json state = {{"version", 1},
                {"stage", stage_ ? Json(StageName(*stage_)) : Json(nullptr)},
                {"step", step_},
                {"completed", completed},
                {"pool_step", pool_step_},
                {"has_lora", has_lora_},
                {"vae_psnr", vae_psnr_},
                {"stage_seconds", stage_seconds_},
                {"stage_settings", stage_settings_},
                {"commands", commands_},
                {"seconds_in_stage", StageWallSeconds()},
                {"counter", checkpoint_counter_},
                {"ema_decay", average_ ? average_->max_decay() : 0.0},
                {"options", Fingerprint(options_, lora_rank_)}};
  FD_RETURN_IF_ERROR(
      fd::model::WriteFileAtomically((tmp / kStateFile).string(), state.dump(2) + "\n"));
  FD_RETURN_IF_ERROR(fd::model::SyncDirectory(tmp.string()));
  const fs::path final_dir = root / name;
  fs::remove_all(final_dir, ec);
  fs::rename(tmp, final_dir, ec);
  if (ec)
    return absl::InternalError(absl::StrCat("cannot rename ", tmp.string(), ": ", ec.message()));
  FD_RETURN_IF_ERROR(fd::model::SyncDirectory(root.string()));
  FD_RETURN_IF_ERROR(fd::model::WriteFileAtomically((root / "LATEST").string(), name + "\n"));
  // Keep the newest keep_checkpoints (names sort by their counter).
  std::vector<std::string> names;
  for (const fs::directory_entry& e : fs::directory_iterator(root, ec)) {
    const std::string n = e.path().filename().string();
    if (e.is_directory() && !n.empty() && n[0] != '.') names.push_back(n);
  }
  std::sort(names.begin(), names.end());
  const int keep = std::max(1, options_.keep_checkpoints);
  for (size_t i = 0; i + keep < names.size(); ++i) fs::remove_all(root / names[i], ec);
  log_->Event("checkpoint", {{"dir", final_dir.string()}});
  return absl::OkStatus();
}

absl::Status Trainer::LoadCheckpoint(const std::string& dir) {
  const fs::path in(dir);
  FD_ASSIGN_OR_RETURN(std::string state_text, ReadTextFile((in / kStateFile).string()));
  const Json state = Json::parse(state_text, nullptr, /*allow_exceptions=*/false);
  if (!state.is_object() || state.value("version", 0) != 1) {
    return absl::InvalidArgumentError(
        absl::StrCat(dir, "/", kStateFile, " is not a trainer state"));
  }
  const Json expected = Fingerprint(options_, lora_rank_);
  const Json saved = state.value("options", Json::object());
  for (const auto& [key, value] : expected.items()) {
    if (key == kStage1UnetLrKey) continue;  // checked below, only where it matters
    if (saved.value(key, Json()) != value) {
      return absl::FailedPreconditionError(
          absl::StrCat("--out ", options_.out_dir, " was trained with ", key, " = ",
                       saved.value(key, Json()).dump(), ", this run has ", value.dump(),
                       "; use the same value or another --out"));
    }
  }
  // Options written only when set (--vae, --prediction_type) must not be
  // dropped by the resuming run either.
  for (const auto& [key, value] : saved.items()) {
    if (key == kStage1UnetLrKey || expected.contains(key)) continue;
    return absl::FailedPreconditionError(
        absl::StrCat("--out ", options_.out_dir, " was trained with ", key, " = ", value.dump(),
                     ", this run without it"
                     "; use the same value or another --out"));
  }
  std::optional<Stage> in_progress;
  for (int s = 0; s < kStageCount; ++s) {
    const std::string name = StageName(static_cast<Stage>(s));
    for (const Json& c : state.value("completed", Json::array())) {
      if (c == name) completed_[s] = true;
    }
    if (state.value("stage", Json()) == name) in_progress = static_cast<Stage>(s);
  }
  // Mid-stage 1, the optimizer's groups depend on --stage1_unet_lr.
  const double saved_unet_lr = saved.value(kStage1UnetLrKey, 0.0);
  const double unet_lr = options_.schedule[static_cast<int>(Stage::kControlNet)].unet_lr;
  if (in_progress == Stage::kControlNet && saved_unet_lr != unet_lr) {
    return absl::FailedPreconditionError(absl::StrCat(
        "--out ", options_.out_dir, " holds an unfinished stage1 trained with ", kStage1UnetLrKey,
        " = ", saved_unet_lr, ", this run has ", unet_lr, "; use the same value or another --out"));
  }
  // The average is the stage's: it resumes only with the decay it began with.
  const double saved_decay = state.value("ema_decay", 0.0);
  if (in_progress && saved_decay != options_.ema_decay) {
    return absl::FailedPreconditionError(
        absl::StrCat("--out ", options_.out_dir, " holds an unfinished ", StageName(*in_progress),
                     " trained with --ema_decay ", saved_decay, ", this run has ",
                     options_.ema_decay, "; use the same value or another --out"));
  }
  if (in_progress && !options_.resume) {
    return absl::FailedPreconditionError(absl::StrCat(
        "--out ", options_.out_dir, " holds an unfinished ", StageName(*in_progress), " (step ",
        state.value("step", 0), "); pass --resume to continue it, or choose another --out"));
  }
  checkpoint_counter_ = state.value("counter", int64_t{0});
  vae_psnr_ = state.value("vae_psnr", 0.0);
  for (const Json& c : state.value("commands", Json::array())) {
    if (c.is_string()) commands_.push_back(c.get<std::string>());
  }
  const Json seconds = state.value("stage_seconds", Json::array());
  for (int s = 0; s < kStageCount && s < static_cast<int>(seconds.size()); ++s) {
    stage_seconds_[s] = seconds[s].get<double>();
  }
  const Json settings = state.value("stage_settings", Json::array());
  for (int s = 0; s < kStageCount && s < static_cast<int>(settings.size()); ++s) {
    stage_settings_[s] = settings[s];
  }
  const torch::Device device = options_.device;
  if (PathExists(in / "vae")) {
    FD_ASSIGN_OR_RETURN(vae_json_, ReadTextFile((in / "vae" / "config.json").string()));
    FD_ASSIGN_OR_RETURN(vae_, fd::model::LoadVae((in / "vae").string(), device, torch::kFloat32));
  }
  if (PathExists(in / "unet")) {
    FD_ASSIGN_OR_RETURN(unet_json_, ReadTextFile((in / "unet" / "config.json").string()));
    FD_ASSIGN_OR_RETURN(unet_, fd::model::LoadUNet((in / "unet").string(), device, torch::kFloat32,
                                                   /*frame_diffuser_input=*/false));
  }
  if (PathExists(in / "controlnet")) {
    FD_ASSIGN_OR_RETURN(controlnet_json_,
                        ReadTextFile((in / "controlnet" / "config.json").string()));
    FD_ASSIGN_OR_RETURN(controlnet_, fd::model::LoadControlNet((in / "controlnet").string(), device,
                                                               torch::kFloat32));
  }
  has_lora_ = state.value("has_lora", false);
  if (has_lora_) {
    FD_ASSIGN_OR_RETURN(fd::model::LoraWeights lora,
                        fd::model::LoadLoraWeights(
                            (in / "controllora" / "pytorch_lora_weights.safetensors").string()));
    FD_RETURN_IF_ERROR(fd::model::ApplyLora(*unet_, lora, fd::model::LoraMode::kLive, 1.0));
  }
  if (PathExists(in / "prompt_embeds.safetensors")) {
    FD_ASSIGN_OR_RETURN(torch::Tensor embeds,
                        fd::model::LoadPromptEmbeds((in / "prompt_embeds.safetensors").string()));
    prompt_embeds_ = embeds.to(device, torch::kFloat32);
  }
  if (!in_progress) {
    log_->Event("loaded", {{"checkpoint", dir}});
    return absl::OkStatus();
  }
  stage_ = in_progress;
  step_ = state.value("step", int64_t{0});
  stage_seconds_before_ = state.value("seconds_in_stage", 0.0);
  stage_clock_ = std::chrono::steady_clock::now();
  pool_step_ = state.value("pool_step", int64_t{-1});
  if (PathExists(in / kPoolFile)) {
    FD_ASSIGN_OR_RETURN(auto tensors, fd::model::LoadSafetensors((in / kPoolFile).string()));
    const torch::Tensor& images = tensors.at("images");
    const torch::Tensor& info = tensors.at("info");
    pool_.clear();
    for (int64_t i = 0; i < images.size(0); ++i) {
      pool_.push_back({static_cast<int>(info[i][0].item<int64_t>()), info[i][1].item<int64_t>(),
                       images[i].clone(), static_cast<int>(info[i][2].item<int64_t>()),
                       info[i][3].item<int64_t>(),
                       static_cast<uint64_t>(info[i][4].item<int64_t>())});
    }
  }
  FD_RETURN_IF_ERROR(ConfigureStage(*stage_));
  const std::string optimizer_path = (in / kOptimizerFile).string();
  FD_RETURN_IF_ERROR(fd::model::TorchCall("load optimizer", [&]() -> absl::Status {
    torch::load(*optimizer_, optimizer_path);
    return absl::OkStatus();
  }));
  if (average_) {
    FD_ASSIGN_OR_RETURN(auto average, fd::model::LoadSafetensors((in / kAverageFile).string()));
    FD_RETURN_IF_ERROR(average_->Load(average));
  }
  log_->Event("resumed", {{"checkpoint", dir}, {"stage", StageName(*stage_)}, {"step", step_}});
  return absl::OkStatus();
}

}  // namespace fd::trainer

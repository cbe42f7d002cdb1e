// The three-stage FrameDiffuser trainer (cgtuebingen/FrameDiffuser train.py +
// train_3_stages.bat @ b39f9af, ../shared/notes/training-reference.md), on
// fd::model's own networks, so the weights it trains are the modules the
// server runs:
//
//   stage 0a (no --base)  AutoencoderKL on the FinalImage frames:
//                         MSE reconstruction + kl_weight * KL (the LDM /
//                         diffusers recipe without LPIPS and GAN); then the
//                         latent scaling factor 1 / std(z) (LDM scale_by_std).
//   stage 0b (no --base)  the base UNet (4-channel conv_in) as a plain latent
//                         diffusion model of the frames with the fixed prompt
//                         embedding: epsilon prediction, uniform t.
//   stage 1               ControlNetModelEx.from_unet; the UNet is frozen;
//                         black irradiance; only the ControlNet trains.
//   stage 2               conv_in widened to 8 channels (zero), ControlLoRA
//                         (full_skip_attn, r, alpha = r, gaussian A, zero B);
//                         previous frame (offset, noise injection) VAE-encoded
//                         and concatenated; irradiance from it. Only the LoRA
//                         trains: the authors' .bat passes --train_controllora
//                         --use_controlnet, which freezes the ControlNet (the
//                         paper says both train; the code wins).
//   stage 3               LoRA + ControlNet train; every `selfcond_every`
//                         steps the current weights render a pool of frames
//                         (DPM-Solver++, half of them chained from the last
//                         pool, so errors compound), and `selfcond_ratio` of
//                         the samples use one as their previous frame.
// Common: the diffusion loss is the plain MSE of the predicted noise (no SNR
// weighting); AdamW (0.9, 0.999, 1e-8, weight decay on every group); groups
// lora_A, lora_B, ControlNet with their own learning rates; cosine schedule
// with warm-up; one global gradient norm clip; gradient accumulation. Frozen
// networks stay float32 masters (the authors' stage-3 bf16 cast is a bug,
// training-reference §3.6).
//
// Output folder (--out) = an environment folder the server loads as it is:
//   unet/ controlnet/ vae/ scheduler/ controllora/pytorch_lora_weights.safetensors
//   prompt_embeds.safetensors environment.json   (written at each stage end)
//   train/log.jsonl, train/loss-<stage>.png, train/validation-<stage>-<step>.png
//   checkpoints/<n>-<stage>-<step>/ (the same layout in float32, plus
//   optimizer.pt, selfcond_pool.safetensors, weight_average.safetensors,
//   trainer_state.json) and checkpoints/LATEST naming the newest.
//   With --ema_decay, train/last-<stage>/ (every stage from stage 1 on,
//   and a decoder fine-tune after it): its last weights, servable, beside
//   the exported average.
//
// Randomness: every draw derives from (seed, stage, index) (sample_builder.h),
// so `--resume` after an interruption reproduces the uninterrupted run.
//
// Thread-safety: a Trainer is used from one thread.
#ifndef FD_TRAINER_TRAINER_H_
#define FD_TRAINER_TRAINER_H_

#include <torch/optim/adamw.h>
#include <torch/types.h>

#include <array>
#include <chrono>
#include <cstdint>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "model/networks/controlnet.h"
#include "model/networks/unet.h"
#include "model/networks/vae.h"
#include "model/pipeline/environment.h"
#include "model/schedulers/scheduler_settings.h"
#include "nlohmann/json.hpp"
#include "trainer/batch_loader.h"
#include "trainer/decoder_latents.h"
#include "trainer/run_log.h"
#include "trainer/sample_builder.h"
#include "trainer/trainer_options.h"
#include "trainer/training_data.h"
#include "trainer/validation.h"
#include "trainer/weight_average.h"

namespace fd::trainer {

// The networks one replica of a training step runs (the masters, or a
// data-parallel copy).
struct Networks {
  fd::model::AutoencoderKL vae{nullptr};
  fd::model::UNet2DConditionModel unet{nullptr};
  fd::model::ControlNetModel controlnet{nullptr};
};

class Trainer {
 public:
  // Loads the data, the base (--base or the preset) and, when --out has a
  // checkpoint, its state: finished stages are kept; an unfinished stage is
  // continued with --resume and refused without it.
  // Errors: the data's (training_data.h); INVALID_ARGUMENT for bad options
  // (naming the option); FAILED_PRECONDITION for an unfinished stage without
  // --resume or a checkpoint made with other options (naming the option);
  // NOT_FOUND / INVALID_ARGUMENT from loading --base or a checkpoint.
  static absl::StatusOr<std::unique_ptr<Trainer>> Create(TrainerOptions options);
  ~Trainer();

  // Runs the configured stages in order; a stage whose results the output
  // folder already holds is skipped (as train_3_stages.bat does). Returns
  // CANCELLED after writing a checkpoint when stop_requested() said so;
  // FAILED_PRECONDITION when a stage's predecessor has not run, or when
  // --decoder_latents_from's environment has another VAE encoder than the
  // one being fine-tuned; that environment's loading errors.
  absl::Status Run();

  // ---- Lower-level steps (Run is made of them; tests drive them directly).
  // Prepares `stage` from the current networks (the stage transition).
  absl::Status BeginStage(Stage stage);
  // One optimizer step (grad_accum micro-batches); returns the mean loss.
  absl::StatusOr<double> TrainStep();
  // Marks the stage finished: checkpoint, export to --out, validation.
  absl::Status EndStage();
  // A self-conditioning round now (stage 3): replaces the pool.
  absl::Status GeneratePool();
  absl::Status SaveCheckpoint();
  // The environment the server would see for the current weights, with
  // another scheduler and step count (the self-conditioning rounds).
  absl::StatusOr<std::shared_ptr<fd::model::Environment>> EnvironmentView(
      fd::model::SchedulerType scheduler, int steps);
  // ... and as exported: UniPC x --inference_steps.
  absl::StatusOr<std::shared_ptr<fd::model::Environment>> EnvironmentView() {
    return EnvironmentView(fd::model::SchedulerType::kUniPCMultistep, options_.inference_steps);
  }
  // Autoregressive render of the first validation sequence (or, without
  // --val, the first training sequence), logged with PSNR/SSIM and written
  // as a contact sheet.
  absl::StatusOr<ValidationResult> Validate();

  std::optional<Stage> stage() const { return stage_; }
  int64_t step() const { return step_; }
  bool completed(Stage stage) const { return completed_[static_cast<int>(stage)]; }
  const TrainingData& data() const { return data_; }
  const std::vector<GeneratedFrame>& pool() const { return pool_; }
  const TrainerOptions& options() const { return options_; }
  fd::model::AutoencoderKL vae() const { return vae_; }
  fd::model::UNet2DConditionModel unet() const { return unet_; }
  fd::model::ControlNetModel controlnet() const { return controlnet_; }
  const torch::Tensor& prompt_embeds() const { return prompt_embeds_; }
  // Parameters the current stage trains (undefined outside a stage).
  const std::vector<torch::Tensor>& trainable() const { return trainable_; }
  double loader_wait_fraction() const;
  // Held-out VAE reconstruction PSNR measured at the end of stage 0a.
  double vae_psnr() const { return vae_psnr_; }
  // The decoder fine-tune's inputs with --decoder_latents_from (empty
  // before that stage begins, and without the flag).
  const std::vector<DecoderLatent>& decoder_latents() const { return decoder_latents_; }

 private:
  explicit Trainer(TrainerOptions options);
  absl::Status Init();
  absl::Status LoadBase();
  absl::Status LoadCheckpoint(const std::string& dir);
  absl::Status ConfigureStage(Stage stage);  // requires_grad, optimizer, replicas, loader
  // Sets requires_grad on `nets` for `stage` and returns the trainable
  // tensors as the optimizer's groups (lora_A, lora_B, ControlNet order).
  absl::StatusOr<std::vector<std::vector<torch::Tensor>>> TrainableGroups(Stage stage,
                                                                          Networks nets);
  // The loss of `batch` (one shard of a micro-batch) on `nets`; its noise
  // and timesteps come from (seed, stage, micro_step, shard).
  absl::StatusOr<torch::Tensor> MicroStepLoss(const TrainingBatch& batch, int64_t micro_step,
                                              int shard, Networks nets);
  // Forward + backward of one micro-batch (split over the replicas);
  // returns its mean loss.
  absl::StatusOr<double> AccumulateMicroStep(const TrainingBatch& batch, int64_t micro_step);
  absl::Status FinishVae();       // scaling factor + PSNR
  absl::Status MeasureVaePsnr();  // held-out reconstruction PSNR -> vae_psnr_
  absl::Status LoadTrainedVae();  // --vae: stage 0a from a trained autoencoder
  // --decoder_latents_from: loads that environment, checks that its encoder
  // is the one being fine-tuned (FAILED_PRECONDITION otherwise) and renders
  // decoder_latents_. Deterministic, so a resumed stage renders them again.
  absl::Status GenerateDecoderLatents();
  // Whether `stage` came with --vae's autoencoder (stage 0a always, its
  // decoder fine-tune when that environment had one) instead of this --out.
  bool FromVaeDir(Stage stage) const;
  absl::Status WriteModelParts(const std::string& dir, torch::Dtype dtype);
  absl::Status ExportEnvironment();
  void ResetLoader();
  const StageSchedule& schedule() const;
  int64_t SelfcondEvery() const;
  static torch::Tensor EncodeLatents(fd::model::AutoencoderKLImpl& vae, const torch::Tensor& images,
                                     at::Generator& gen);

  TrainerOptions options_;
  TrainingData data_;
  TrainingData validation_data_;
  std::string scheduler_json_;
  // The scheduler config's prediction_type: what the denoiser's output is
  // regressed on (epsilon, v_prediction or sample).
  std::string prediction_type_ = "epsilon";
  // --vae from an environment trained here: its stage0-vae (and, when it
  // had one, stage0-decoder) record entry and commands, by stage.
  std::map<Stage, nlohmann::json> vae_sources_;
  // With --decoder_latents_from, the --vae environment's own decoder
  // fine-tune (its record entry and commands), which this run's follows.
  nlohmann::json previous_decoder_;
  std::vector<DecoderLatent> decoder_latents_;
  double decoder_latents_psnr_ = 0;
  std::string unet_json_;
  std::string controlnet_json_;
  std::string vae_json_;
  std::vector<int64_t> controlnet_embedding_channels_;
  int64_t lora_rank_ = 0;
  // 3 * f * f with --basecolor_patches (f: the VAE's downsampling), else 0.
  int64_t basecolor_patch_channels_ = 0;
  torch::Tensor alphas_cumprod_;  // [T] float32 CPU

  fd::model::AutoencoderKL vae_{nullptr};
  fd::model::UNet2DConditionModel unet_{nullptr};
  fd::model::ControlNetModel controlnet_{nullptr};
  torch::Tensor prompt_embeds_;  // [1, T, D] float32
  bool has_lora_ = false;
  double vae_psnr_ = 0;

  std::array<bool, kStageCount> completed_{};
  std::optional<Stage> stage_;
  std::string last_stage_ = "start";  // names validations between stages
  int64_t step_ = 0;
  std::unique_ptr<torch::optim::AdamW> optimizer_;
  std::vector<double> group_lrs_;
  std::vector<torch::Tensor> trainable_;
  // --ema_decay: the average of trainable_ (null when off or outside a stage).
  std::unique_ptr<WeightAverage> average_;
  struct Replica {
    Networks nets;
    std::vector<torch::Tensor> trainable;  // in trainable_'s order
  };
  std::vector<Replica> replicas_;  // options_.replicas - 1 copies
  std::vector<GeneratedFrame> pool_;
  int64_t pool_step_ = -1;
  std::unique_ptr<BatchLoader> loader_;
  std::unique_ptr<TrainingBatch> overfit_batch_;  // the last batch (--overfit_one_batch)
  double step_seconds_ = 0;
  double wait_seconds_ = 0;
  // Wall-clock seconds per finished stage, and of the running stage before
  // this process (a resumed stage); environment.json records them.
  std::array<double, kStageCount> stage_seconds_{};
  // What each finished stage was trained with (StageSettings at its end;
  // persisted, so that a later command's flags do not rewrite the record).
  std::array<nlohmann::json, kStageCount> stage_settings_{};
  double stage_seconds_before_ = 0;
  std::chrono::steady_clock::time_point stage_clock_;
  double StageWallSeconds() const;
  nlohmann::json TrainingRecord() const;
  nlohmann::json StageSettings(Stage stage) const;  // this run's options for `stage`
  // The command lines of every run that trained into --out, oldest first
  // (a later stage may be run by another command; environment.json lists all).
  std::vector<std::string> commands_;
  bool trained_this_run_ = false;
  int64_t checkpoint_counter_ = 0;
  std::unique_ptr<RunLog> log_;
};

}  // namespace fd::trainer

#endif  // FD_TRAINER_TRAINER_H_

// Everything a training run is configured with (framediffuser-train's
// flags, trainer/cli.h). Defaults: the authors' train_3_stages.bat where it
// carries over to a small CPU run (AdamW wd 1e-2, clip 1.0, cosine with
// warm-up, LoRA rank = the preset's, self-conditioning ratio 0.5 / chaining
// 0.5), scaled step counts and learning rates for the tiny presets.
#ifndef FD_TRAINER_TRAINER_OPTIONS_H_
#define FD_TRAINER_TRAINER_OPTIONS_H_

#include <torch/types.h>

#include <array>
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "client_sdk/dataset.h"
#include "trainer/sample_builder.h"

namespace fd::trainer {

// Optimizer steps, warm-up and learning rates of one stage.
struct StageSchedule {
  int64_t steps = 0;
  int64_t warmup = 0;
  double lr = 1e-4;            // LoRA (stages 2-3), the network (stage 0), ControlNet (stage 1)
  double controlnet_lr = 0.0;  // stage 3's ControlNet group; 0 = lr
  // Stage 1 only: > 0 also trains the UNet, in its own group at this rate.
  // 0 keeps it frozen, as the authors do; a base UNet trained here for
  // minutes (not SD 1.5) then learns to take the ControlNet's residuals.
  double unet_lr = 0.0;
};

struct TrainerOptions {
  std::vector<std::string> data_dirs;        // --data (repeatable)
  std::vector<std::string> validation_dirs;  // --val (held-out sequences)
  std::string out_dir;                       // --out
  std::string base_dir;                      // --base: a diffusers SD folder (skips stage 0)
  // --vae: a trained AutoencoderKL (a vae/ folder, or an environment folder
  // holding one) that replaces stage 0a, so an environment's autoencoder can
  // be kept while everything after it is retrained. Without --base.
  std::string vae_dir;
  std::string preset = "tiny";  // widths of the fresh networks (model/presets/presets.h)
  int width = 64;
  int height = 64;
  std::vector<Stage> stages;  // in order; empty = all
  std::array<StageSchedule, kStageCount> schedule;
  int batch_size = 4;
  int grad_accum = 1;
  int64_t lora_rank = 0;  // 0 = the preset's
  // Latent channels of fresh networks (VAE latent, UNet in/out, ControlNet
  // input); 0 = the preset's (4, SD1.5's). More channels at the same 8x
  // downsampling raise the autoencoder's ceiling and keep the authors'
  // ControlNet-Ex condition encoder (three stride-2 convs) unchanged.
  int64_t latent_channels = 0;
  // Stage 0's VAE trains on random square crops of this size (0 = whole
  // frames): the autoencoder is fully convolutional apart from its
  // mid-block attention, and crops make its steps several times cheaper.
  int vae_crop = 0;
  uint64_t seed = 0;
  double weight_decay = 1e-2;
  double max_grad_norm = 1.0;
  double kl_weight = 1e-6;
  bool sky_injection = true;
  // false (--no-irradiance): channel 9 stays black in stages 2-3 and at
  // inference (environment.json "irradiance": "black"), the paper's Table 4.
  bool irradiance = true;
  // --basecolor_patches: from stage 1 on, the UNet's conv_in also takes the
  // condition's basecolor pixel-unshuffled to the latent grid
  // (UNet2DConditionConfig::basecolor_patch_channels): the albedo's colours
  // reach the UNet directly, not only through the ControlNet. Fixed by the
  // stage-0 UNet's config: a folder trained with it needs it on every
  // command, one trained without refuses it. Its weights train with the UNet
  // (--stage1_unet_lr) in stage 1 and through conv_in's LoRA in stages 2-3.
  bool basecolor_patches = false;
  // environment.json's sky_mode (how the server fills sky pixels at
  // inference); empty: sky_image with sky injection, else none.
  std::string sky_mode;
  // The command that started the run, recorded in environment.json.
  std::string command_line;
  double max_noise_sigma = 0.2;
  // --max_blur_sigma (sample_builder.h BlurImage): stages 2-3 blur the
  // ground-truth previous frame by up to this many pixels; 0: off.
  double max_blur_sigma = 0.0;
  // --recolour_probability (sample_builder.h): the share of stage 1-3 samples
  // whose albedo channels are reordered and frames relit to match.
  double recolour_probability = 0.0;
  // --flip_probability / --flip_plane_normal (sample_builder.h MirrorSample):
  // the share of stage 1-3 samples flipped left to right, and the plane the
  // world-space normals are reflected in (normalised; required with a
  // probability above 0, since only the data knows where its sun is).
  double flip_probability = 0.0;
  std::optional<PlaneNormal> flip_plane_normal;
  // --pixel_loss_weight: the diffusion stages' loss adds this times the
  // pixel MSE of the clean latents the prediction implies, decoded by the
  // frozen VAE, against the frame (in [-1, 1]). The latent MSE charges a
  // wrong colour 10-30x less than a wrong content per unit of pixel error
  // (bench/latent_colour_probe.cc); the decoded error charges both alike.
  // 0: off (the authors' loss).
  double pixel_loss_weight = 0.0;
  // --ema_decay D: every stage keeps an exponential moving average of the
  // weights it trains (trainer/weight_average.h: decay min(D, n / (9 + n))
  // after step n) and ends with it: the export, the validation, the end
  // checkpoint and the next stage hold the average; the last weights of a
  // stage ending with a servable folder (stage 1 on, or a decoder fine-tune
  // after it) are exported beside it, train/last-<stage>/. In
  // [0, 1); 0: off (the authors'). Recorded per stage; a stage started with
  // one value resumes only with it.
  double ema_decay = 0.0;
  // --colour_latent_scale K: stage 0's VAE also learns to make its last three
  // latent channels (a posterior sample) equal K times each latent cell's
  // block mean colour (the frame in [-1, 1], average-pooled by the
  // downsampling factor), so the diffusion stages' latent MSE charges a
  // wrong colour directly; the other channels carry the rest. The folder
  // stays a plain AutoencoderKL. 0: off (the authors' VAE loss).
  double colour_latent_scale = 0.0;
  // --decoder_latents_from ENV: the decoder fine-tune (stage0-decoder) trains
  // on the latents that ENV, a finished environment with the same encoder
  // (give --vae ENV), renders for the training frames at its serving
  // settings, autoregressively from ground-truth keyframes
  // (trainer/decoder_latents.h), instead of the encoder's latents. Empty:
  // the encoder's (the fine-tune of street's eighth round).
  std::string decoder_latents_from;
  int decoder_chains = 64;        // --decoder_chains: chains rendered
  int decoder_chain_frames = 16;  // --decoder_chain_frames: frames per chain
  int max_offset = 2;
  // What fresh networks learn to predict (diffusers' prediction_type):
  // "epsilon" (SD1.5's and the authors'), or "v_prediction" (SD2's
  // v = sqrt(a) eps - sqrt(1 - a) x0), whose loss weights the clean-image
  // error evenly across noise levels instead of by the SNR, so the
  // highest-noise steps, where every sampler starts, train too. Written to
  // scheduler_config.json, which every sampler (and diffusers) reads.
  // Empty: epsilon, or the --base's scheduler config.
  std::string prediction_type;
  // How the diffusion stages draw timesteps (sample_builder.h).
  TimestepSampling timestep_sampling = TimestepSampling::kUniform;
  std::string prompt = "A photorealistic scene";
  fd::client::ExrValues exr_values = fd::client::ExrValues::kWire;

  // Stage 3 self-conditioning (0 = derived: every = stage3 steps / 15, the
  // .bat's 2000 of 30000; count = the authors' 500 frames per 2000 x 8
  // samples, i.e. one frame per 32 samples of a round, 4..500, at most the
  // training frame count).
  int64_t selfcond_every = 0;
  int selfcond_count = 0;
  double selfcond_ratio = 0.5;
  double selfcond_chain_ratio = 0.5;
  int selfcond_steps = 40;  // DPM-Solver++ steps (the authors' generated_conditioning_steps)

  // The exported environment.json's default UniPC steps per frame (the
  // authors' inference: 10). Clients may still ask for any count up to the
  // server's --max_steps; docs/EVALUATION.md measures the choice.
  int inference_steps = 10;

  int64_t checkpoint_every = 0;  // optimizer steps; 0 = only at stage ends
  int64_t validate_every = 0;    // 0 = only at stage ends
  int validation_frames = 8;     // frames rendered autoregressively per validation
  int keep_checkpoints = 2;
  int64_t log_every = 10;
  bool progress_bar = true;

  torch::Device device = torch::kCPU;
  torch::Dtype dtype = torch::kFloat32;  // bfloat16: autocast on CUDA
  int threads = 1;
  // Data parallelism on the CPU: each micro-batch is split over this many
  // copies of the networks, each on its own thread with one intra-op thread
  // (a second intra-op thread adds little at these widths: docs/BENCHMARKS.md).
  // Changes the random streams, so it is part of a checkpoint's options.
  int replicas = 1;
  // Recompute the UNet's and ControlNet's resnets and transformer blocks in
  // backward instead of keeping their activations (diffusers'
  // enable_gradient_checkpointing, the authors' --gradient_checkpointing):
  // less memory for a slower step, identical results (docs/BENCHMARKS.md).
  // The authors pass it in every stage (train_3_stages.bat: SD 1.5 at 512²
  // on a GPU); off by default here, where the CPU presets are not memory
  // bound and it only costs time.
  bool gradient_checkpointing = false;
  int loader_threads = 1;
  int prefetch = 4;
  torch::Dtype export_dtype = torch::kFloat32;
  bool resume = false;
  // Debugging (Lightning's overfit_batches): every step trains on the first
  // batch with the same noise and timesteps; the loss must then fall.
  bool overfit_one_batch = false;

  // Polled after every optimizer step (SIGINT/SIGTERM in main): when it
  // returns true, a checkpoint is written and Run returns CANCELLED.
  std::function<bool()> stop_requested;
};

// The defaults for `stage` (steps scaled for CPU runs of the tiny preset).
StageSchedule DefaultSchedule(Stage stage);

}  // namespace fd::trainer

#endif  // FD_TRAINER_TRAINER_OPTIONS_H_

// framediffuser-train's flags; see cli.h.
#include "trainer/cli.h"

#include <algorithm>
#include <cmath>
#include <functional>
#include <map>
#include <string>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "model/presets/presets.h"

namespace fd::trainer {
namespace {

std::string Quoted(const std::string& value) {
  return absl::StrCat("'", value.size() > 64 ? value.substr(0, 64) + "..." : value, "'");
}

absl::Status Bad(const std::string& flag, const std::string& expected, const std::string& value) {
  return absl::InvalidArgumentError(
      absl::StrCat(flag, ": expected ", expected, ", got ", Quoted(value)));
}

template <typename Int>
std::function<absl::Status(const std::string&, const std::string&)> IntFlag(Int* out, Int min) {
  return [out, min](const std::string& flag, const std::string& v) -> absl::Status {
    Int parsed;
    if (!absl::SimpleAtoi(v, &parsed) || parsed < min) {
      return Bad(flag, absl::StrCat("an integer >= ", min), v);
    }
    *out = parsed;
    return absl::OkStatus();
  };
}

std::function<absl::Status(const std::string&, const std::string&)> DoubleFlag(double* out,
                                                                               double min) {
  return [out, min](const std::string& flag, const std::string& v) -> absl::Status {
    double parsed;
    if (!absl::SimpleAtod(v, &parsed) || !(parsed >= min)) {
      return Bad(flag, absl::StrCat("a number >= ", min), v);
    }
    *out = parsed;
    return absl::OkStatus();
  };
}

absl::StatusOr<std::vector<Stage>> StagesOf(const std::string& command) {
  if (command == "all") return std::vector<Stage>{};
  // The decoder fine-tune runs only with --decoder_steps (Trainer::Create).
  if (command == "stage0") return std::vector<Stage>{Stage::kVae, Stage::kDecoder, Stage::kBase};
  if (command == "decoder") return std::vector<Stage>{Stage::kDecoder};
  if (command == "stage1") return std::vector<Stage>{Stage::kControlNet};
  if (command == "stage2") return std::vector<Stage>{Stage::kControlLora};
  if (command == "stage3") return std::vector<Stage>{Stage::kSelfConditioning};
  return absl::InvalidArgumentError(
      absl::StrCat("unknown command ", Quoted(command),
                   " (commands: all, stage0, stage1, stage2, stage3, decoder)"));
}

}  // namespace

std::string Usage() {
  return R"(usage: framediffuser-train COMMAND --data DIR [--data DIR ...] --out DIR [flags]

Trains a FrameDiffuser environment (the authors' three stages) on G-buffer
sequences in the authors' dataset layout; --out becomes an environment folder
that framediffuser-server serves as it is (--model_repository entry).

commands:
  all       every stage in order (stages already in --out are skipped)
  stage0    without --base: the VAE, then the base UNet, from the frames
            (with --decoder_steps, the decoder fine-tune between them)
  stage1    ControlNet on the G-buffer, black irradiance, UNet frozen
  stage2    ControlLoRA on the previous frame (irradiance, noise injection)
  stage3    self-conditioning on the model's own frames (LoRA + ControlNet)
  decoder   fine-tune the VAE's decoder on whole frames, encoder frozen (the
            latents, and so every diffusion stage, stay valid); needs
            --decoder_steps, and runs at any point after stage0's VAE

data and output:
  --data DIR            a training sequence, or a folder of sequences (repeatable)
  --val DIR             held-out sequence(s) for validation renders (repeatable)
  --out DIR             output environment folder (checkpoints inside)
  --base DIR            start from a diffusers SD folder (unet/ vae/ scheduler/ and
                        text_encoder/+tokenizer/ or prompt_embeds.safetensors)
  --vae DIR             keep a trained autoencoder (a vae/ folder or an environment
                        holding one) instead of training stage 0's VAE
  --preset NAME         widths of fresh networks: tiny, small, compact, sd15 (default tiny)
  --resolution WxH      training resolution, multiples of 8 (default 64x64)
  --exr_values MODE     wire (EXR already [0,1]) or linear (scenegen's EXRs)
  --prompt TEXT         the environment's prompt (default "A photorealistic scene")
  --resume              continue an interrupted stage from its last checkpoint
  --sky_mode MODE       environment.json's sky fill at inference: sky_image,
                        previous_output or none (default: sky_image, or none
                        with --no-sky-injection)

optimisation (per stage S = vae, base, stage1, stage2, stage3, decoder):
  --S_steps N --S_warmup N --S_lr X    optimizer steps, warm-up steps, learning rate
                                       (--decoder_steps: 0, off, by default)
  --stage3_controlnet_lr X             stage 3's ControlNet group (default 1e-4)
  --stage1_unet_lr X                   stage 1 also trains the UNet at this rate
                                       (default: frozen, as the authors do)
  --batch_size N (4)  --grad_accum N (1)  --seed N (0)  --lora_rank R (preset's)
  --latent_channels N (preset's: 4)  --vae_crop N (0: whole frames; stage 0's VAE)
  --weight_decay X (1e-2)  --max_grad_norm X (1.0)  --kl_weight X (1e-6)
  --max_noise_sigma X (0.2)  --max_offset N (2)  --no-sky-injection
  --max_blur_sigma X    stages 2-3: the ground-truth previous frame is blurred by a
                        Gaussian of sigma ~ U(0, X) pixels before the noise (default
                        0: off), as the model's own frames are smeared
  --no-irradiance       black irradiance in every stage and at inference (ablation)
  --pixel_loss_weight W  the diffusion stages' loss adds W times the pixel MSE of the
                        predicted clean latents decoded by the frozen VAE (default 0;
                        a decoder pass per step: slower)
  --ema_decay D         every stage ends with an exponential moving average of the
                        weights it trained (diffusers' EMAModel: decay min(D, n/(9+n))
                        after step n; default 0: off, the last weights); a stage
                        ending with a servable folder (stage 1 on) also exports its
                        last weights to train/last-<stage>/
  --colour_latent_scale K  stage 0's VAE: its last three latent channels learn
                        to equal K times each 8x8 block's mean colour (default 0:
                        off), so the diffusion loss charges a wrong colour; with
                        --latent_channels 7, four channels carry the rest
  --recolour_probability P  stages 1-3: a sample's albedo channels are reordered
                        with probability P (default 0) and its frames relit to
                        match, so colours are read from the basecolor
  --flip_probability P  stages 1-3: a sample is flipped left to right with
                        probability P (default 0), its world-space normals
                        reflected in the plane of --flip_plane_normal X,Y,Z
                        (normalised; required with P > 0): a vertical plane
                        through the sun's direction keeps the light as it is
                        (1,0,0 for camera-space normals)
  --basecolor_patches   the UNet's conv_in also takes the basecolor pixel-unshuffled
                        to the latent grid (3*8*8 channels after the previous latent;
                        this project's extension, in unet/config.json), so the albedo's
                        colours need not pass through the ControlNet; give it from
                        stage 0 on (with --stage1_unet_lr to train it in stage 1)
  --timestep_sampling uniform|cubic  diffusion timesteps: uniform (the authors')
                        or cubic, t = (1 - u^3) T (T2I-Adapter): more high-noise
                        steps, where a frame's layout is decided
  --prediction_type epsilon|v_prediction  what fresh networks predict: the noise
                        (SD1.5's, the authors'; default) or v (SD2's), which
                        trains the highest-noise steps as much as the others

decoder fine-tune on the model's own frames (with decoder --decoder_steps N):
  --decoder_latents_from ENV  train the decoder on the latents that the finished
                        environment ENV renders for --data's frames at its serving
                        settings (autoregressive chains from ground-truth
                        keyframes), not the encoder's; give --vae ENV too
  --decoder_chains N (64)  --decoder_chain_frames N (16)  chains and their length

self-conditioning (stage 3):
  --selfcond_every N    steps between generation rounds (default stage3_steps/15)
  --selfcond_count N    frames per round (default: one per 32 samples of a round)
  --selfcond_ratio X    fraction of samples on generated frames (0.5)
  --selfcond_chain_ratio X  fraction of a round chained from the last round (0.5)
  --selfcond_steps N    DPM-Solver++ steps per generated frame (40)

running:
  --checkpoint_every N  optimizer steps between checkpoints (default: stage ends)
  --validate_every N    steps between validation renders (default: stage ends)
  --validation_frames N frames per validation render (8)
  --keep_checkpoints N  newest checkpoints kept (2)
  --log_every N (10)  --no-progress
  --overfit_one_batch   debugging: train on one batch (fixed noise); the loss must fall
  --device cpu|cuda:N (cpu)  --dtype float32|bfloat16 (bfloat16: CUDA autocast)
  --threads N (1)  --loader_threads N (1)  --prefetch N (4)
  --replicas N (1)      split each batch over N single-threaded copies of the
                        networks and sum their gradients (CPU data parallelism)
  --gradient_checkpointing  recompute UNet/ControlNet blocks in backward instead of
                        storing their activations (less memory, slower steps)
  --export_dtype float32|float16 (float32)
  --inference_steps N   environment.json's default UniPC steps per frame (10, the
                        authors'; clients may ask for others)

SIGINT / SIGTERM write a checkpoint and exit with status 130; --resume continues.
)";
}

absl::StatusOr<ParsedArgs> ParseTrainArgs(const std::vector<std::string>& args) {
  ParsedArgs parsed;
  TrainerOptions& o = parsed.options;
  for (int s = 0; s < kStageCount; ++s) o.schedule[s] = DefaultSchedule(static_cast<Stage>(s));
  using Setter = std::function<absl::Status(const std::string&, const std::string&)>;
  std::map<std::string, Setter> flags;
  std::map<std::string, std::function<void()>> switches = {
      {"--resume", [&] { o.resume = true; }},
      {"--no-sky-injection", [&] { o.sky_injection = false; }},
      {"--no-irradiance", [&] { o.irradiance = false; }},
      {"--basecolor_patches", [&] { o.basecolor_patches = true; }},
      {"--no-progress", [&] { o.progress_bar = false; }},
      {"--overfit_one_batch", [&] { o.overfit_one_batch = true; }},
      {"--gradient_checkpointing", [&] { o.gradient_checkpointing = true; }},
  };
  auto append = [](std::vector<std::string>* out) -> Setter {
    return [out](const std::string&, const std::string& v) {
      out->push_back(v);
      return absl::OkStatus();
    };
  };
  auto text = [](std::string* out) -> Setter {
    return [out](const std::string&, const std::string& v) {
      *out = v;
      return absl::OkStatus();
    };
  };
  flags["--data"] = append(&o.data_dirs);
  flags["--val"] = append(&o.validation_dirs);
  flags["--out"] = text(&o.out_dir);
  flags["--base"] = text(&o.base_dir);
  flags["--vae"] = text(&o.vae_dir);
  flags["--prompt"] = text(&o.prompt);
  flags["--preset"] = [&](const std::string& flag, const std::string& v) -> absl::Status {
    const std::vector<std::string> names = fd::model::CheckpointPresetNames();
    if (std::find(names.begin(), names.end(), v) == names.end()) {
      return Bad(flag, absl::StrJoin(names, ", "), v);
    }
    o.preset = v;
    return absl::OkStatus();
  };
  flags["--resolution"] = [&](const std::string& flag, const std::string& v) -> absl::Status {
    std::vector<std::string> parts = absl::StrSplit(v, 'x');
    int w = 0, h = 0;
    if (parts.size() != 2 || !absl::SimpleAtoi(parts[0], &w) || !absl::SimpleAtoi(parts[1], &h) ||
        w <= 0 || h <= 0 || w % 8 != 0 || h % 8 != 0) {
      return Bad(flag, "WxH with positive multiples of 8", v);
    }
    o.width = w;
    o.height = h;
    return absl::OkStatus();
  };
  flags["--sky_mode"] = [&](const std::string& flag, const std::string& v) -> absl::Status {
    if (v != "sky_image" && v != "previous_output" && v != "none") {
      return Bad(flag, "sky_image, previous_output or none", v);
    }
    o.sky_mode = v;
    return absl::OkStatus();
  };
  flags["--timestep_sampling"] = [&](const std::string& flag,
                                     const std::string& v) -> absl::Status {
    if (v == "uniform") {
      o.timestep_sampling = TimestepSampling::kUniform;
    } else if (v == "cubic") {
      o.timestep_sampling = TimestepSampling::kCubic;
    } else {
      return Bad(flag, "uniform or cubic", v);
    }
    return absl::OkStatus();
  };
  flags["--prediction_type"] = [&](const std::string& flag, const std::string& v) -> absl::Status {
    if (v != "epsilon" && v != "v_prediction") return Bad(flag, "epsilon or v_prediction", v);
    o.prediction_type = v;
    return absl::OkStatus();
  };
  flags["--exr_values"] = [&](const std::string& flag, const std::string& v) -> absl::Status {
    if (v == "wire") {
      o.exr_values = fd::client::ExrValues::kWire;
    } else if (v == "linear") {
      o.exr_values = fd::client::ExrValues::kLinear;
    } else {
      return Bad(flag, "wire or linear", v);
    }
    return absl::OkStatus();
  };
  const char* stage_flags[kStageCount] = {"vae", "base", "stage1", "stage2", "stage3", "decoder"};
  for (int s = 0; s < kStageCount; ++s) {
    StageSchedule& sched = o.schedule[s];
    flags[absl::StrCat("--", stage_flags[s], "_steps")] = IntFlag<int64_t>(&sched.steps, 1);
    flags[absl::StrCat("--", stage_flags[s], "_warmup")] = IntFlag<int64_t>(&sched.warmup, 0);
    flags[absl::StrCat("--", stage_flags[s], "_lr")] = DoubleFlag(&sched.lr, 1e-12);
  }
  flags["--stage3_controlnet_lr"] =
      DoubleFlag(&o.schedule[static_cast<int>(Stage::kSelfConditioning)].controlnet_lr, 1e-12);
  flags["--stage1_unet_lr"] =
      DoubleFlag(&o.schedule[static_cast<int>(Stage::kControlNet)].unet_lr, 1e-12);
  flags["--batch_size"] = IntFlag<int>(&o.batch_size, 1);
  flags["--grad_accum"] = IntFlag<int>(&o.grad_accum, 1);
  flags["--seed"] = IntFlag<uint64_t>(&o.seed, 0);
  flags["--lora_rank"] = IntFlag<int64_t>(&o.lora_rank, 1);
  flags["--latent_channels"] = IntFlag<int64_t>(&o.latent_channels, 1);
  flags["--vae_crop"] = IntFlag<int>(&o.vae_crop, 8);
  flags["--weight_decay"] = DoubleFlag(&o.weight_decay, 0);
  flags["--max_grad_norm"] = DoubleFlag(&o.max_grad_norm, 1e-12);
  flags["--kl_weight"] = DoubleFlag(&o.kl_weight, 0);
  flags["--max_noise_sigma"] = DoubleFlag(&o.max_noise_sigma, 0);
  flags["--max_blur_sigma"] = DoubleFlag(&o.max_blur_sigma, 0);
  flags["--max_offset"] = IntFlag<int>(&o.max_offset, 1);
  flags["--recolour_probability"] = DoubleFlag(&o.recolour_probability, 0);
  flags["--flip_probability"] = DoubleFlag(&o.flip_probability, 0);
  flags["--flip_plane_normal"] = [&](const std::string& flag,
                                     const std::string& v) -> absl::Status {
    const std::vector<std::string> parts = absl::StrSplit(v, ',');
    PlaneNormal n{};
    bool ok = parts.size() == 3;
    for (size_t i = 0; ok && i < 3; ++i) ok = absl::SimpleAtod(parts[i], &n[i]);
    const double norm = ok ? std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]) : 0.0;
    if (!ok || !std::isfinite(norm) || norm < 1e-6) {
      return Bad(flag, "three numbers X,Y,Z, not all 0", v);
    }
    for (double& c : n) c /= norm;
    o.flip_plane_normal = n;
    return absl::OkStatus();
  };
  flags["--pixel_loss_weight"] = DoubleFlag(&o.pixel_loss_weight, 0);
  flags["--ema_decay"] = DoubleFlag(&o.ema_decay, 0);
  flags["--colour_latent_scale"] = DoubleFlag(&o.colour_latent_scale, 0);
  flags["--decoder_latents_from"] = text(&o.decoder_latents_from);
  flags["--decoder_chains"] = IntFlag<int>(&o.decoder_chains, 1);
  flags["--decoder_chain_frames"] = IntFlag<int>(&o.decoder_chain_frames, 1);
  flags["--selfcond_every"] = IntFlag<int64_t>(&o.selfcond_every, 1);
  flags["--selfcond_count"] = IntFlag<int>(&o.selfcond_count, 1);
  flags["--selfcond_ratio"] = DoubleFlag(&o.selfcond_ratio, 0);
  flags["--selfcond_chain_ratio"] = DoubleFlag(&o.selfcond_chain_ratio, 0);
  flags["--selfcond_steps"] = IntFlag<int>(&o.selfcond_steps, 1);
  flags["--inference_steps"] = IntFlag<int>(&o.inference_steps, 1);
  flags["--checkpoint_every"] = IntFlag<int64_t>(&o.checkpoint_every, 1);
  flags["--validate_every"] = IntFlag<int64_t>(&o.validate_every, 1);
  flags["--validation_frames"] = IntFlag<int>(&o.validation_frames, 1);
  flags["--keep_checkpoints"] = IntFlag<int>(&o.keep_checkpoints, 1);
  flags["--log_every"] = IntFlag<int64_t>(&o.log_every, 1);
  flags["--threads"] = IntFlag<int>(&o.threads, 1);
  flags["--replicas"] = IntFlag<int>(&o.replicas, 1);
  flags["--loader_threads"] = IntFlag<int>(&o.loader_threads, 1);
  flags["--prefetch"] = IntFlag<int>(&o.prefetch, 1);
  flags["--device"] = [&](const std::string& flag, const std::string& v) -> absl::Status {
    int index = 0;
    if (v == "cpu") {
      o.device = torch::kCPU;
    } else if (absl::StartsWith(v, "cuda:") && absl::SimpleAtoi(v.substr(5), &index) &&
               index >= 0) {
      o.device = torch::Device(torch::kCUDA, static_cast<c10::DeviceIndex>(index));
    } else {
      return Bad(flag, "cpu or cuda:N", v);
    }
    return absl::OkStatus();
  };
  flags["--dtype"] = [&](const std::string& flag, const std::string& v) -> absl::Status {
    if (v == "float32") {
      o.dtype = torch::kFloat32;
    } else if (v == "bfloat16") {
      o.dtype = torch::kBFloat16;
    } else {
      return Bad(flag, "float32 or bfloat16", v);
    }
    return absl::OkStatus();
  };
  flags["--export_dtype"] = [&](const std::string& flag, const std::string& v) -> absl::Status {
    if (v == "float32") {
      o.export_dtype = torch::kFloat32;
    } else if (v == "float16") {
      o.export_dtype = torch::kFloat16;
    } else {
      return Bad(flag, "float32 or float16", v);
    }
    return absl::OkStatus();
  };

  std::map<std::string, bool> seen;
  bool have_command = false;
  for (size_t i = 0; i < args.size(); ++i) {
    std::string flag = args[i];
    if (flag == "--help" || flag == "-h") {
      parsed.help = true;
      return parsed;
    }
    if (!absl::StartsWith(flag, "-")) {
      if (have_command) {
        return absl::InvalidArgumentError(
            absl::StrCat("unexpected argument ", Quoted(flag), " (one command only)"));
      }
      absl::StatusOr<std::vector<Stage>> stages = StagesOf(flag);
      if (!stages.ok()) return stages.status();
      o.stages = *stages;
      have_command = true;
      continue;
    }
    std::string value;
    bool has_value = false;
    if (const size_t eq = flag.find('='); eq != std::string::npos) {
      value = flag.substr(eq + 1);
      flag = flag.substr(0, eq);
      has_value = true;
    }
    if (auto s = switches.find(flag); s != switches.end()) {
      if (has_value) return absl::InvalidArgumentError(absl::StrCat(flag, " takes no value"));
      s->second();
      continue;
    }
    auto f = flags.find(flag);
    if (f == flags.end()) {
      return absl::InvalidArgumentError(
          absl::StrCat("unknown flag ", Quoted(flag), " (see --help)"));
    }
    if (!has_value) {
      if (i + 1 >= args.size())
        return absl::InvalidArgumentError(absl::StrCat(flag, " needs a value"));
      value = args[++i];
    }
    if (absl::Status set = f->second(flag, value); !set.ok()) return set;
    seen[flag] = true;
  }
  if (!have_command) {
    return absl::InvalidArgumentError(
        "no command given (all, stage0, stage1, stage2, stage3, decoder)");
  }
  if (o.data_dirs.empty()) return absl::InvalidArgumentError("--data is required");
  if (o.out_dir.empty()) return absl::InvalidArgumentError("--out is required");
  for (int s = 0; s < kStageCount; ++s) {
    const std::string warmup_flag = absl::StrCat("--", stage_flags[s], "_warmup");
    if (!seen[warmup_flag]) {
      // The default warm-up keeps its share of the stage's steps.
      const StageSchedule d = DefaultSchedule(static_cast<Stage>(s));
      // A stage that is off by default (the decoder fine-tune) warms up 5 %.
      o.schedule[s].warmup =
          d.steps > 0 ? o.schedule[s].steps * d.warmup / d.steps : o.schedule[s].steps / 20;
    }
    if (o.schedule[s].warmup > o.schedule[s].steps) {
      return absl::InvalidArgumentError(
          absl::StrCat("--", stage_flags[s], "_warmup (", o.schedule[s].warmup, ") exceeds --",
                       stage_flags[s], "_steps (", o.schedule[s].steps, ")"));
    }
  }
  return parsed;
}

}  // namespace fd::trainer

// The model presets: the network widths of `tiny` (tests), `small` (quick
// experiments), `compact` (the shipped environments: 3 UNet levels over a
// 16x16 latent at 128x128) and `sd15` (the real Stable Diffusion 1.5 UNet / ControlNet /
// VAE shapes) as diffusers config.json texts (GetPresetConfigs; the trainer
// builds its fresh networks from them), and random-weight FrameDiffuser
// checkpoints of a preset in the authors' diffusers layout (MakeCheckpoint;
// framediffuser-make-checkpoint is its command line):
//
//   <out>/unet/        config.json + diffusion_pytorch_model.safetensors
//                      UNet2DConditionModelEx: config in_channels 4, conv_in
//                      weight [C0, 8, 3, 3] (noisy + previous-frame latent)
//   <out>/controlnet/  ControlNetModelEx (10-channel G-buffer, 9-conv encoder)
//   <out>/vae/         AutoencoderKL (scaling_factor 0.18215)
//   <out>/scheduler/scheduler_config.json   SD1.5's PNDM json
//   <out>/controllora/pytorch_lora_weights.safetensors
//                      PEFT keys unet.<module>.lora_A/B.weight for every
//                      Linear/Conv2d except to_q/to_k/to_v/to_out.0
//                      (FrameDiffuser's "full_skip_attn"), alpha = rank
//   <out>/prompt_embeds.safetensors   `prompt_embeds` [1, 77, cross_dim]
//
// EVERY parameter is random (no zero-initialised zero-convs or conv_out, no
// zero conv_in channels 4-7), so a dropped layer cannot go unnoticed:
// conv/linear weights N(0, 1/fan_in), biases N(0, 0.05^2), norm weights
// 1 + N(0, 0.1^2) and biases N(0, 0.1^2); LoRA A N(0, 1/fan_in), B
// N(0, 0.3^2 / r) (the fd_pipeline golden's recipe). The same options give
// byte-identical files.
#ifndef FD_MODEL_PRESETS_PRESETS_H_
#define FD_MODEL_PRESETS_PRESETS_H_

#include <torch/types.h>

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace fd::model {

struct MakeCheckpointOptions {
  std::string preset = "tiny";  // tiny | small | compact | sd15
  std::string out_dir;          // created if missing; existing files are replaced
  uint64_t seed = 0;
  // Stored dtype of the weights (float32, float16 or bfloat16).
  torch::Dtype dtype = torch::kFloat32;
  int64_t lora_rank = 0;  // 0: the preset's rank
};

// The preset names, in order of size.
std::vector<std::string> CheckpointPresetNames();

// The config.json texts of a preset (what MakeCheckpoint writes).
struct PresetConfigs {
  std::string unet;
  std::string controlnet;
  std::string vae;
  int64_t lora_rank = 0;
  int64_t prompt_tokens = 77;
};
// INVALID_ARGUMENT for an unknown preset (the message lists the presets).
absl::StatusOr<PresetConfigs> GetPresetConfigs(const std::string& preset);

// Writes the checkpoint. Builds and writes one network at a time (the sd15
// preset needs about 2x the UNet's float32 size, ~7 GB, of memory).
// Errors: INVALID_ARGUMENT (preset, dtype, rank), INTERNAL (I/O, torch).
// Thread-safety: none needed beyond distinct out_dirs.
absl::Status MakeCheckpoint(const MakeCheckpointOptions& options);

}  // namespace fd::model

#endif  // FD_MODEL_PRESETS_PRESETS_H_

// Writing checkpoint folders in the diffusers / FrameDiffuser layout that
// LoadUNet, LoadControlNet, LoadVae, LoadLoraWeights and LoadEnvironment
// read: `<dir>/config.json` + `<dir>/diffusion_pytorch_model.safetensors` per
// network, the ControlLoRA file with PEFT keys, SD1.5's scheduler config.
// Used by the presets (random weights) and the trainer (trained weights).
//
// Every file is written atomically: to a temporary name in the same folder,
// flushed to disk (fsync), then renamed over the old file, so a reader or a
// crash sees the old file or the new one, never a torn one.
//
// Thread-safety: the functions are stateless; concurrent writers must use
// distinct paths. No exception escapes (torch errors become INTERNAL).
#ifndef FD_MODEL_CHECKPOINT_CHECKPOINT_WRITER_H_
#define FD_MODEL_CHECKPOINT_CHECKPOINT_WRITER_H_

#include <torch/nn/module.h>
#include <torch/types.h>

#include <map>
#include <string>
#include <string_view>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace fd::model {

// SD1.5's scheduler/scheduler_config.json (a PNDM json; the environment
// builds its samplers and the trainer its DDPM training schedule from it).
extern const char kSd15SchedulerConfigJson[];

// Writes `bytes` to `path` atomically (temp file, fsync, rename).
// Errors: INTERNAL naming the file (I/O).
absl::Status WriteFileAtomically(const std::string& path, std::string_view bytes);

// Creates `dir` and its parents. INTERNAL naming the folder on failure.
absl::Status CreateDirectories(const std::string& dir);

// fsync of a folder, so that renames inside it are durable. INTERNAL.
absl::Status SyncDirectory(const std::string& dir);

// Writes `dir`/config.json (`config_text`) and
// `dir`/diffusion_pytorch_model.safetensors holding every named parameter of
// `module` (its diffusers state-dict keys) converted to `dtype`.
// Errors: INVALID_ARGUMENT (dtype), INTERNAL (I/O, torch).
absl::Status WriteModelFolder(torch::nn::Module& module, const std::string& config_text,
                              const std::string& dir, torch::Dtype dtype);

// FrameDiffuser's default_full_skip_attn_lora_target_modules: every Linear
// and Conv2d of the UNet except the attention projections
// to_q / to_k / to_v / to_out.0. `name` is a module path in the UNet.
bool IsFullSkipAttnTarget(const std::string& name);

// The live LoRA adapters of `unet` (lora_layers.h) as PEFT keys
// `unet.<module>.lora_A.weight` / `.lora_B.weight`, converted to `dtype`
// (what diffusers' save_lora_weights writes for the authors' ControlLoRA).
// Requires every adapted layer to carry exactly one live adapter with
// scaling 1 (alpha = r, the authors' setting); INVALID_ARGUMENT otherwise,
// naming the module. INTERNAL on torch errors.
absl::StatusOr<std::map<std::string, torch::Tensor>> LiveLoraStateDict(torch::nn::Module& unet,
                                                                       torch::Dtype dtype);

// Saves a tensor map as safetensors with the {"format": "pt"} metadata
// diffusers writes. Errors as SaveSafetensors.
absl::Status WriteSafetensorsFile(const std::string& path,
                                  const std::map<std::string, torch::Tensor>& tensors);

}  // namespace fd::model

#endif  // FD_MODEL_CHECKPOINT_CHECKPOINT_WRITER_H_

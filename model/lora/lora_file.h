// Reading LoRA / ControlLoRA weight files (pytorch_lora_weights.safetensors,
// controllora.safetensors) into one normalised form, and the merged weight
// delta of one adapted module. Applying the adapters to a network (merged or
// live) is model/lora/lora_layers.h's job; this file only parses and does the math.
//
// Accepted key formats (diffusers' save_lora_weights output, see
// diffusers/utils/state_dict_utils.py convert_state_dict_to_diffusers, and
// the PEFT format it leaves for non-attention modules):
//   unet.<module>.lora_A.weight / unet.<module>.lora_B.weight   (PEFT)
//   unet.<module>.lora.down.weight / unet.<module>.lora.up.weight  (diffusers)
//   unet.<module>.alpha   (optional scalar; alpha = rank when absent)
// with or without the "unet." prefix. lora_A = down, lora_B = up.
// Shapes: Linear A [r, in], B [out, r]; Conv2d A [r, in, kh, kw] (the base
// conv's kernel), B [out, r, 1, 1].
//
// Note: for files without alphas whose modules have DIFFERENT ranks, diffusers
// v0.31 (get_peft_kwargs) uses the rank of the first module as one global
// lora_alpha; here every module's alpha defaults to its own rank (scaling 1),
// which is what PEFT training with lora_alpha = r (FrameDiffuser, ControlLoRA
// v3) saved.
#ifndef FD_MODEL_LORA_LORA_FILE_H_
#define FD_MODEL_LORA_LORA_FILE_H_

#include <torch/types.h>

#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "model/checkpoint/file_source.h"
#include "model/checkpoint/safetensors.h"

namespace fd::model {

// The adapter of one module (PEFT LoraLayer: lora_A = down, lora_B = up).
struct LoraModuleWeights {
  torch::Tensor down;  // lora_A: [r, in] or [r, in, kh, kw]
  torch::Tensor up;    // lora_B: [out, r] or [out, r, 1, 1]
  int64_t rank = 0;
  double alpha = 0.0;  // = rank when the file has no `<module>.alpha`

  bool is_conv() const { return down.dim() == 4; }
  // alpha / r: the factor PEFT applies on top of the adapter scale.
  double scaling() const { return alpha / static_cast<double>(rank); }
  // The shape of the base weight this adapter fits: [out, in] or
  // [out, in, kh, kw].
  std::vector<int64_t> WeightShape() const;
};

// A parsed LoRA file. Immutable after loading; safe to share across threads.
struct LoraWeights {
  std::string source;  // the file path (for messages)
  // Module path inside the UNet (no "unet." prefix), e.g.
  // "down_blocks.0.resnets.0.conv1" -> its adapter.
  std::map<std::string, LoraModuleWeights> modules;
};

// Reads and validates a LoRA file: every module must have both halves with
// consistent shapes (2-D A/B, or 4-D A with a 1x1 4-D B, equal ranks),
// floating-point tensors and at most one key format; alpha keys must be
// scalars belonging to an adapted module.
// Errors: NOT_FOUND (no file), INVALID_ARGUMENT naming the file and the key
// (corrupt safetensors, unknown key, missing partner, bad shapes, keys of
// another component such as text_encoder), INTERNAL (I/O).
absl::StatusOr<LoraWeights> LoadLoraWeights(const std::string& path,
                                            const FileSource& files = DiskFiles());
absl::StatusOr<LoraWeights> ParseLoraWeights(const SafetensorsFile& file);
// The same for tensors in memory; `source` names them in errors.
absl::StatusOr<LoraWeights> ParseLoraWeights(const std::map<std::string, torch::Tensor>& tensors,
                                             const std::string& source);

// The merged-weight delta of one module:
//   Linear: scale * (alpha / r) * (B @ A)                       -> [out, in]
//   Conv2d: scale * (alpha / r) * einsum('or,rihw->oihw', B[:, :, 0, 0], A)
//                                                               -> [out, in, kh, kw]
// so that W' = W + delta (biases unchanged). Computed in float32 (float64 when
// the adapter is float64) on the adapter's device; the caller casts to the
// weight's dtype. INVALID_ARGUMENT for inconsistent shapes, INTERNAL for
// LibTorch errors.
absl::StatusOr<torch::Tensor> LoraDelta(const LoraModuleWeights& weights, double scale = 1.0);

}  // namespace fd::model

#endif  // FD_MODEL_LORA_LORA_FILE_H_

// Attaching a parsed LoRA / ControlLoRA file (lora_file.h) to a network whose
// Linear/Conv2d layers are LoraLinear/LoraConv2d (lora_layers.h): merged into
// the base weights (default, zero runtime cost) or live (unmerged, scale
// changeable), as FrameDiffuser's inference runs its ControlLoRA.
#ifndef FD_MODEL_LORA_APPLY_LORA_H_
#define FD_MODEL_LORA_APPLY_LORA_H_

#include <torch/nn/module.h>

#include "absl/status/status.h"
#include "model/lora/lora_file.h"
#include "model/lora/lora_layers.h"

namespace fd::model {

enum class LoraMode {
  // W' = W + scale * alpha/r * B@A at apply time (biases unchanged). The
  // scale is baked in; SetLoraScale does not change it.
  kMerged,
  // y = base(x) + B(A(x)) * (scale * alpha/r); the scale stays changeable
  // with SetLoraScale (PEFT set_scale / set_extra_condition_scale).
  kLive,
};

// Attaches every adapter of `lora` to the layer of `root` at the same module
// path (LoraWeights paths carry no "unet." prefix; e.g. "conv_in",
// "down_blocks.0.attentions.0.transformer_blocks.0.ff.net.2"). In kLive mode
// the live scale of every layer of `root` is set to `scale`.
// Nothing is changed unless every adapter fits: paths that name no
// LoraLinear/LoraConv2d of `root`, and adapters whose shapes do not fit their
// layer, give INVALID_ARGUMENT listing all of them (and naming the file).
// INTERNAL on torch errors (the network may then be partly modified).
// Not thread-safe: no forward may run on `root` meanwhile.
absl::Status ApplyLora(torch::nn::Module& root, const LoraWeights& lora, LoraMode mode,
                       double scale = 1.0);

}  // namespace fd::model

#endif  // FD_MODEL_LORA_APPLY_LORA_H_

// Strict loading of a checkpoint (a .safetensors file or a tensor map) into a
// torch::nn::Module, the C++ counterpart of PyTorch's
// `module.load_state_dict(state_dict, strict=True)`.
//
// The module's named_parameters() and named_buffers() are the targets; every
// target must receive a tensor of its exact shape and every checkpoint tensor
// must have a target. Otherwise the error lists ALL missing keys, unexpected
// keys and shape mismatches (with both shapes), so one run shows everything
// that is wrong with a checkpoint. Values are converted to each target's
// dtype and device (e.g. an F16 checkpoint into a float32 module on CUDA).
#ifndef FD_MODEL_CHECKPOINT_STATE_DICT_LOADER_H_
#define FD_MODEL_CHECKPOINT_STATE_DICT_LOADER_H_

#include <torch/nn/module.h>
#include <torch/types.h>

#include <cstddef>
#include <functional>
#include <map>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "model/checkpoint/safetensors.h"

namespace fd::model {

struct LoadOptions {
  // Maps a checkpoint key to the module's parameter/buffer name (e.g. to
  // strip a "unet." prefix). An empty result drops the key (it is neither
  // loaded nor reported as unexpected). Unset: names are used as they are.
  std::function<std::string(const std::string& checkpoint_key)> rename_key;

  // Called, before anything is written, for each tensor whose shape differs
  // from its target's: may return a tensor of the target's shape (e.g. the
  // UNet loader zero-pads a [C, 4, 3, 3] conv_in weight to [C, 8, 3, 3] as the
  // authors' add_extra_conditions does), the tensor unchanged (-> reported as
  // a shape mismatch) or an error (returned as is). `name` is the target name
  // after rename_key; `target` is the module's tensor (read-only).
  std::function<absl::StatusOr<torch::Tensor>(const std::string& name, torch::Tensor loaded,
                                              const torch::Tensor& target)>
      adapt_shape;

  // Targets that may stay absent from the checkpoint (they keep their
  // current values), e.g. a buffer that newer exporters no longer save.
  std::function<bool(const std::string& name)> allow_missing;
  // Checkpoint keys (before renaming) that are ignored when no target has
  // their name.
  std::function<bool(const std::string& checkpoint_key)> ignore_unexpected;

  // At most this many names are listed per kind of problem; the rest are
  // counted ("... and 12 more").
  size_t max_listed = 20;
};

// Loads `file` into `module` (parameters and buffers, recursively).
//
// Errors: INVALID_ARGUMENT listing the missing keys, unexpected keys, shape
// mismatches and dtype-kind mismatches (floating point vs integer/bool),
// naming the file; or whatever an adapt_shape hook returns. On these errors
// the module is unchanged (everything is validated before the first write).
// INTERNAL for a LibTorch failure while copying (the module may then be
// partially loaded).
// Thread-safety: the caller must not use `module` concurrently.
absl::Status LoadStateDict(torch::nn::Module& module, const SafetensorsFile& file,
                           const LoadOptions& options = {});

// The same for tensors already in memory; `source` names them in errors.
absl::Status LoadStateDict(torch::nn::Module& module,
                           const std::map<std::string, torch::Tensor>& tensors,
                           const LoadOptions& options = {},
                           const std::string& source = "state dict");

}  // namespace fd::model

#endif  // FD_MODEL_CHECKPOINT_STATE_DICT_LOADER_H_

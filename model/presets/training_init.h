// What training adds to fd::model's networks: fresh weights, the authors'
// stage transitions (ControlNetModelEx.from_unet, add_extra_conditions, PEFT's
// LoRA injection) and the requires_grad split between frozen and trainable
// weights. The networks are the ones the server runs (unet.h, controlnet.h,
// vae.h, lora_layers.h); nothing here changes their forward.
//
// References: diffusers v0.31.0 ControlNetModel.from_unet
// (models/controlnets/controlnet.py), FrameDiffuser model.py
// (ControlNetModelEx.from_unet, UNet2DConditionModelEx.add_extra_conditions),
// PEFT tuners/lora/layer.py reset_lora_parameters("gaussian").
//
// Thread-safety: none; call while no forward runs on the networks.
// No exception escapes: torch errors become INTERNAL.
#ifndef FD_MODEL_PRESETS_TRAINING_INIT_H_
#define FD_MODEL_PRESETS_TRAINING_INIT_H_

#include <torch/nn/module.h>
#include <torch/types.h>

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "model/networks/controlnet.h"
#include "model/networks/unet.h"
#include "model/networks/vae.h"

namespace fd::model {

// PyTorch's default initialisation, which diffusers models keep when built
// from a config: Linear / Conv2d weights kaiming_uniform(a = sqrt(5)), i.e.
// U(-1/sqrt(fan_in), 1/sqrt(fan_in)), biases U(-1/sqrt(fan_in),
// 1/sqrt(fan_in)); GroupNorm / LayerNorm weight 1, bias 0. Deterministic per
// seed. INTERNAL if a parameter belongs to no known layer type.
absl::Status InitializeDefaultWeights(torch::nn::Module& module, uint64_t seed);

// Sets requires_grad on every parameter of `module`.
void SetRequiresGrad(torch::nn::Module& module, bool requires_grad);

// The ControlNet config.json text for a UNet config.json text, as
// ControlNetModel.from_unet + ControlNetModelEx write it: the UNet's shared
// keys, `_class_name` ControlNetModelEx, 10 conditioning (G-buffer) channels
// and `embedding_channels` (the from_unet default (16, 32, 96, 256)).
// INVALID_ARGUMENT for text that is not a UNet config.
absl::StatusOr<std::string> ControlNetConfigJsonFromUNet(
    const std::string& unet_config_json,
    const std::vector<int64_t>& embedding_channels = {16, 32, 96, 256});

// ControlNetModelEx.from_unet(unet, gbuffer_channels=10): conv_in,
// time_embedding, down_blocks and mid_block copied from `unet` (which must
// have a base 4-channel conv_in), every controlnet_down_blocks / mid 1x1 conv
// zero, the 9-conv G-buffer encoder default-initialised (seed) with its LAST
// conv zero. A fresh ControlNet therefore adds exactly zero residuals.
// INVALID_ARGUMENT when the shapes do not match (config of another UNet).
absl::StatusOr<ControlNetModel> ControlNetFromUNet(UNet2DConditionModelImpl& unet,
                                                   const ControlNetConfig& config, uint64_t seed);

// add_extra_conditions: a copy of the base `unet` (same device/dtype) whose
// conv_in takes 2 * out_channels + basecolor_patch_channels inputs (the
// copy's config says basecolor_patch_channels), the extra ones with zero
// weights, so the copy's prediction ignores the previous-frame latent (and
// the patches) until trained.
// Parameters are copied (the result shares no storage with `unet`).
// INVALID_ARGUMENT if `unet` is already widened or basecolor_patch_channels
// is negative or not a multiple of 3.
absl::StatusOr<UNet2DConditionModel> WidenConvIn(UNet2DConditionModelImpl& unet,
                                                 int64_t basecolor_patch_channels = 0);

// PEFT LoraConfig(r=rank, lora_alpha=rank, init_lora_weights="gaussian",
// target_modules=full_skip_attn): one live adapter on every Linear / Conv2d of
// `unet` except to_q/to_k/to_v/to_out.0, lora_A ~ N(0, (1/rank)^2), lora_B = 0
// (so the prediction is unchanged), scaling 1, float32 on the UNet's device,
// requires_grad. Returns the A tensors and the B tensors (module order).
// INVALID_ARGUMENT for rank < 1 or a UNet that already has live adapters.
struct TrainableLora {
  std::vector<torch::Tensor> down;  // lora_A
  std::vector<torch::Tensor> up;    // lora_B
};
absl::StatusOr<TrainableLora> AddTrainableControlLora(UNet2DConditionModelImpl& unet, int64_t rank,
                                                      uint64_t seed);

// The live adapters of `unet` (e.g. loaded by ApplyLora in live mode) made
// trainable (requires_grad), in the same order as AddTrainableControlLora.
// INVALID_ARGUMENT when `unet` has none.
absl::StatusOr<TrainableLora> TrainableLiveLora(UNet2DConditionModelImpl& unet);

// Independent copies (same config, parameters copied, no shared storage;
// live LoRA adapters copied too, requires_grad as in the original), on the
// original's device and dtype: the data-parallel replicas of a CPU training
// step. INTERNAL on torch errors.
absl::StatusOr<UNet2DConditionModel> CopyUNet(UNet2DConditionModelImpl& unet);
absl::StatusOr<ControlNetModel> CopyControlNet(ControlNetModelImpl& controlnet);
absl::StatusOr<AutoencoderKL> CopyVae(AutoencoderKLImpl& vae);

}  // namespace fd::model

#endif  // FD_MODEL_PRESETS_TRAINING_INIT_H_

// FrameDiffuser's per-frame conditioning, as the authors' inference code
// computes it (github cgtuebingen/FrameDiffuser @ b39f9af5):
//   * irradiance    inference.py compute_irradiance_map: luma(previous output)
//                   / (luma(previous RAW basecolor) + 1e-6) where the albedo
//                   luma > 0.01, else 2.0; clamp [0, 2]; / 2; then quantised
//                   to uint8 by TRUNCATION (`(x * 255).astype(np.uint8)`)
//                   before it becomes a PIL 'L' image;
//   * sky fill      gbuffer_masking_utils.fill_black_pixels_in_basecolor:
//                   pixels whose basecolor channels are ALL < 10 and whose
//                   depth is < 10 (uint8) take the sky source's pixel;
//   * G-buffer      GBufferProcessor.create_g_buffer_tensor: basecolor (sky
//                   filled) 3, normals 3, depth 1, roughness 1, metallic 1
//                   (an all-zero image when absent), irradiance 1, each
//                   ToTensor (u8 / 255) + Normalize(0.5, 0.5) -> [-1, 1].
// The arithmetic is float32 in the reference's order of operations, so
// results from uint8 inputs are bit-identical to the reference on CPU.
//
// Image tensors are [N, C, H, W] on any device, either uint8 (0..255, what
// the reference reads from PNGs) or floating point in [0, 1]. Floating-point
// images are first quantised like the reference's PIL images:
// round-half-to-even(x * 255), the conversion the pipeline applies to its
// output image. What becomes the ControlNet condition (PackCondition,
// BuildFrameCondition) must have H and W multiples of `size_multiple`
// (default 8: the latent is 1/8 size); the single operations accept any size.
//
// All functions are stateless and thread-safe. Errors: INVALID_ARGUMENT
// naming the input (wrong rank or channel count, mismatched batch/size/device,
// a size that is not a multiple of size_multiple, unsupported dtype, NaN/Inf
// or values outside [0, 1] in a floating-point image); INTERNAL for a
// LibTorch failure.
#ifndef FD_MODEL_PIPELINE_CONDITIONING_H_
#define FD_MODEL_PIPELINE_CONDITIONING_H_

#include <torch/types.h>

#include <string_view>

#include "absl/status/statusor.h"

namespace fd::model {

// Number of channels of the ControlNet condition.
inline constexpr int64_t kConditionChannels = 10;

// Validates `image` ([N, channels, H, W], uint8 or float in [0, 1]) and
// returns it as uint8; `name` appears in error messages.
absl::StatusOr<torch::Tensor> ToUint8Image(const torch::Tensor& image, std::string_view name,
                                           int64_t channels);

// compute_irradiance_map(final, albedo): float32 [N, 1, H, W] in [0, 1].
// final_rgb: the previous output frame (or the keyframe); albedo_rgb: the
// previous frame's RAW basecolor (not sky filled). Both [N, 3, H, W].
absl::StatusOr<torch::Tensor> ComputeIrradiance(const torch::Tensor& final_rgb,
                                                const torch::Tensor& albedo_rgb);

// (irradiance * 255) truncated to uint8, as the reference stores it.
// irradiance: floating point [N, 1, H, W] in [0, 1] (as ComputeIrradiance
// returns it).
absl::StatusOr<torch::Tensor> QuantizeIrradiance(const torch::Tensor& irradiance);

// fill_black_pixels_in_basecolor: uint8 [N, 3, H, W].
// basecolor, sky: [N, 3, H, W]; depth: [N, 1, H, W].
absl::StatusOr<torch::Tensor> FillSky(const torch::Tensor& basecolor, const torch::Tensor& depth,
                                      const torch::Tensor& sky);

// The G-buffer of one batch of frames ([N, C, H, W] each).
struct GBuffer {
  torch::Tensor basecolor;  // [N, 3, H, W]
  torch::Tensor normals;    // [N, 3, H, W]
  torch::Tensor depth;      // [N, 1, H, W]
  torch::Tensor roughness;  // [N, 1, H, W]
  torch::Tensor metallic;   // [N, 1, H, W]; undefined = all-zero image
};

// create_g_buffer_tensor's packing: float32 [N, 10, H, W] in [-1, 1] from
// the G-buffer as given (sky fill, if any, already applied to basecolor) and
// the uint8 irradiance [N, 1, H, W].
absl::StatusOr<torch::Tensor> PackCondition(const GBuffer& gbuffer,
                                            const torch::Tensor& irradiance_u8,
                                            int64_t size_multiple = 8);

// Where the basecolor's sky pixels (basecolor and depth black) come from.
enum class SkyFillMode {
  kSkyImage,        // a sky image the client sends with every frame (the
                    // reference fills from the ground-truth FinalImage)
  kPreviousOutput,  // the previously generated frame
  kNone,            // no fill (the reference's enable_injection = false)
};

struct FrameConditionInputs {
  GBuffer gbuffer;  // the frame being generated
  SkyFillMode sky_fill = SkyFillMode::kNone;
  torch::Tensor sky_image;  // [N, 3, H, W]; required for kSkyImage
  // Irradiance source: the previous output frame (or the keyframe) and the
  // previous frame's raw basecolor, [N, 3, H, W] each. Both undefined:
  // black irradiance (all-zero image), the G-buffer-only start mode.
  // previous_output is also the sky source of kPreviousOutput.
  torch::Tensor previous_output;
  torch::Tensor previous_basecolor;
  // Black irradiance even when previous_output is given (it then only
  // serves as the sky source): models trained without irradiance (the
  // paper's Table 4 ablation, and stage 1 alone).
  bool black_irradiance = false;
  // H and W must be multiples of this (8: VAE/ControlNet downsampling).
  int64_t size_multiple = 8;
};

struct FrameCondition {
  torch::Tensor condition;      // float32 [N, 10, H, W] in [-1, 1]
  torch::Tensor basecolor;      // uint8 [N, 3, H, W], after the sky fill
  torch::Tensor irradiance;     // float32 [N, 1, H, W] in [0, 1] (zeros when black)
  torch::Tensor irradiance_u8;  // uint8 [N, 1, H, W], what channel 9 encodes
};

// Sky fill + irradiance + packing for one batch of frames.
// Additional INVALID_ARGUMENT cases: sky_image missing for kSkyImage,
// previous_output missing for kPreviousOutput, only one of
// previous_output/previous_basecolor given.
absl::StatusOr<FrameCondition> BuildFrameCondition(const FrameConditionInputs& inputs);

// The UNet's basecolor patches (UNet2DConditionConfig::basecolor_patch_channels,
// this project's extension): the condition's basecolor channels (0-2, in
// [-1, 1], sky filled) pixel-unshuffled by `factor`, the VAE's downsampling:
// [N, 10, H, W] -> [N, 3 * factor * factor, H / factor, W / factor], same
// dtype and device. Each latent cell sees its factor x factor block of
// albedo as it is, not through the ControlNet's encoder.
// INVALID_ARGUMENT unless `condition` is [N, >= 3, H, W] with H and W
// multiples of `factor` >= 1.
absl::StatusOr<torch::Tensor> BasecolorPatches(const torch::Tensor& condition, int64_t factor);

}  // namespace fd::model

#endif  // FD_MODEL_PIPELINE_CONDITIONING_H_

// Conversion between a session's images (shared ImageBuffers: the decoded
// G-buffer, the state's previous frame) and the model's PipelineInput /
// FrameOutput tensors (model/pipeline/frame_pipeline.h). The one place that
// knows both sides (nothing above session/ sees a tensor):
//   - keyframe start and re-seed: the keyframe is the "previous frame"; a
//     keyframe without a basecolor uses this frame's own basecolor;
//   - G-buffer-only start: no previous frame (black irradiance, zero
//     previous latent);
//   - a kept previous latent ("previous_latent": "reuse") replaces the VAE
//     encode of the previous frame;
//   - the per-frame seeds: FrameSeed(session seed, frame counter)
//     (frame_seed.h), split into the VAE-noise seed and the x_T seed;
//   - the session's enums mapped to the model's (model_enums.h).
#ifndef FD_SESSION_PIPELINE_INPUT_BUILDER_H_
#define FD_SESSION_PIPELINE_INPUT_BUILDER_H_

#include <torch/types.h>

#include <cstdint>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "base/image_buffer.h"
#include "model/pipeline/frame_pipeline.h"
#include "session/frame_seed.h"
#include "session/session.h"
#include "session/session_settings.h"

namespace fd::session {

// The G-buffer of one frame: HWC images of the session's size, uint8
// (0..255) or float32 in [0, 1], as the server's decoder produced them
// (server/frame_input.h validates them once, at the edge). Value type; the
// pixels are shared, not copied.
struct FrameGBuffer {
  ImageBuffer basecolor;  // 3 channels, raw (not sky filled)
  ImageBuffer normals;    // 3 channels
  ImageBuffer depth;      // 1 channel
  ImageBuffer roughness;  // 1 channel
  ImageBuffer metallic;   // 1 channel; empty = zeros
  ImageBuffer sky;        // 3 channels; required when sky_mode is kClientImage
};

// Domains that separate the two noise draws of one frame.
inline constexpr uint64_t kVaeNoiseSeedDomain = 0x7661'655f'6e6f'6973ULL;   // "vae_nois"
inline constexpr uint64_t kInitNoiseSeedDomain = 0x696e'6974'5f6e'6f69ULL;  // "init_noi"

// Seed of the VAE latent_dist.sample() noise of the frame whose frame seed
// is `frame_seed` (FrameContext::frame_seed). Pure function; part of the
// reproducibility contract (changing it changes every session's frames).
constexpr uint64_t VaeNoiseSeed(uint64_t frame_seed) {
  return Mix64(frame_seed ^ kVaeNoiseSeedDomain);
}
// Seed of the initial latent noise x_T of that frame.
constexpr uint64_t InitNoiseSeed(uint64_t frame_seed) {
  return Mix64(frame_seed ^ kInitNoiseSeedDomain);
}

// The request of the frame described by `context`. The images become CPU
// tensors that VIEW the buffers (no copy; each tensor keeps its buffer
// alive), so the request may outlive the context and the job. The images
// are validated at the edge (server/frame_input.h) and only asserted here;
// model::FramePipeline::Begin, a public API, checks them again and names the
// field. INTERNAL on a LibTorch failure. Thread-safety: pure function.
absl::StatusOr<model::PipelineInput> BuildPipelineInput(const SessionSettings& settings,
                                                        const FrameContext& context,
                                                        const FrameGBuffer& gbuffer);

// The frame's basecolor as the session stores it (uint8 HWC RGB): a uint8
// buffer is shared as is, a float32 one is quantised as round(x * 255)
// (half to even) clamped to 0..255 (the reference reads 8-bit PNGs, so float
// inputs are an extension). INVALID_ARGUMENT unless it is the session's
// W x H x 3.
absl::StatusOr<ImageBuffer> BasecolorBuffer(const SessionSettings& settings,
                                            const ImageBuffer& basecolor);

// The model's uint8 [H, W, 3] output (FrameOutput::image_uint8) as a buffer
// that shares the tensor's storage (no copy when it is a contiguous CPU
// tensor). INVALID_ARGUMENT for another dtype or shape.
absl::StatusOr<ImageBuffer> OutputImage(const SessionSettings& settings,
                                        const torch::Tensor& image_uint8);

// The model's float32 [1, 3, H, W] output (FrameOutput::image_float) as an
// HWC float32 buffer. INVALID_ARGUMENT for another dtype or shape.
absl::StatusOr<ImageBuffer> OutputFloatImage(const SessionSettings& settings,
                                             const torch::Tensor& image_float);

// The model's denoised latent [1, C, h, w] (FrameOutput::latent, any
// device) as a session LatentBuffer (copied to the CPU: C*h*w floats).
// INVALID_ARGUMENT for another dtype or rank; INTERNAL on a LibTorch failure.
absl::StatusOr<LatentBuffer> OutputLatent(const torch::Tensor& latent);

// A [1, C, h, w] float32 CPU tensor viewing `latent`'s values (the tensor
// keeps them alive and must not be written to); undefined when empty.
// Throws what LibTorch throws (callers wrap it in TorchCall).
torch::Tensor LatentView(const LatentBuffer& latent);

// A [H, W, C] CPU tensor (uint8 or float32) viewing `image`'s bytes; the
// tensor keeps the buffer alive and must not be written to. Undefined for an
// empty buffer. Throws what LibTorch throws (callers wrap it in TorchCall).
torch::Tensor TensorView(const ImageBuffer& image);

// A [H, W, C] or [H, W] CPU tensor, uint8 or float32, as a buffer sharing its
// (contiguous) storage. INVALID_ARGUMENT for another dtype, rank or device.
absl::StatusOr<ImageBuffer> BufferFromTensor(const torch::Tensor& hwc);

}  // namespace fd::session

#endif  // FD_SESSION_PIPELINE_INPUT_BUILDER_H_

// Conversion between a session's state (uint8 HWC buffers, session.h) and the
// model's FrameRequest / FrameOutput tensors (model/frame_pipeline.h). The
// one place that knows both sides:
//   - keyframe start and re-seed: the keyframe is the "previous frame"; a
//     keyframe without a basecolor uses this frame's own basecolor;
//   - G-buffer-only start: no previous frame (black irradiance, zero
//     previous latent);
//   - the per-frame seeds: FrameSeed(session seed, frame counter)
//     (frame_seed.h), split into the VAE-noise seed and the x_T seed;
//   - the session's enums mapped to the model's.
#ifndef FD_SESSION_FRAME_REQUEST_BUILDER_H_
#define FD_SESSION_FRAME_REQUEST_BUILDER_H_

#include <torch/types.h>

#include <cstdint>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "model/frame_pipeline.h"
#include "session/frame_seed.h"
#include "session/session.h"
#include "session/session_settings.h"

namespace fd::session {

// The G-buffer of one frame, HWC CPU tensors of the session's size, uint8
// (0..255) or floating point in [0, 1] (as model::FrameRequest takes them).
// Value type; tensors are shared, not copied.
struct FrameGBuffer {
  torch::Tensor basecolor;  // [H, W, 3], raw (not sky filled)
  torch::Tensor normals;    // [H, W, 3]
  torch::Tensor depth;      // [H, W] or [H, W, 1]
  torch::Tensor roughness;  // [H, W] or [H, W, 1]
  torch::Tensor metallic;   // [H, W] or [H, W, 1]; undefined = zeros
  torch::Tensor sky;        // [H, W, 3]; required when sky_mode is kClientImage
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

model::SchedulerType ToModelScheduler(SchedulerKind kind);
model::SkyFillMode ToModelSkyMode(SkyMode mode);

// The request of the frame described by `context` (read inside
// Session::ReadFrameContext: the previous frame and basecolor are COPIED
// into new tensors, so the request outlives the callback). INVALID_ARGUMENT
// naming the field when a G-buffer tensor is missing or its height/width is
// not the session's, or the sky image is missing for kClientImage.
// Thread-safety: pure function (creates CPU tensors).
absl::StatusOr<model::FrameRequest> BuildFrameRequest(const SessionSettings& settings,
                                                      const FrameContext& context,
                                                      const FrameGBuffer& gbuffer);

// The frame's basecolor as the session stores it (uint8 HWC RGB): a uint8
// tensor is copied as is, a float one is quantised as round(x * 255)
// clamped to 0..255 (the reference reads 8-bit PNGs, so float inputs are an
// extension). INVALID_ARGUMENT unless it is [H, W, 3].
absl::StatusOr<std::vector<uint8_t>> BasecolorBytes(const SessionSettings& settings,
                                                    const torch::Tensor& basecolor);

// A float [1, 3, H, W] tensor (FrameOutput::image_float) as HWC floats.
// INVALID_ARGUMENT for another dtype or shape.
absl::StatusOr<std::vector<float>> FloatImageHwc(const SessionSettings& settings,
                                                 const torch::Tensor& image_float);

// A uint8 [H, W, 3] tensor (FrameOutput::image_uint8) as bytes.
// INVALID_ARGUMENT for another dtype or shape.
absl::StatusOr<std::vector<uint8_t>> ImageBytes(const SessionSettings& settings,
                                                const torch::Tensor& image_uint8);

}  // namespace fd::session

#endif  // FD_SESSION_FRAME_REQUEST_BUILDER_H_

// FramePipeline: renders a batch of FrameDiffuser frames, one item per
// session. A port of the authors' StableDiffusionDualControlPipeline.__call__
// (cgtuebingen/FrameDiffuser pipeline.py @ b39f9af5) together with the
// per-frame preprocessing of inference.py (GBufferProcessor,
// compute_irradiance_map, fill_black_pixels_in_basecolor; model/pipeline/conditioning.h):
//
//   prev = previous frame /255*2-1 -> vae.encode -> (mean + std*noise) * sf
//   cond = G-buffer (sky filled) + irradiance(prev frame, prev basecolor),
//          normalised to [-1, 1], 10 channels
//   x_T  = init_noise * init_noise_sigma
//   per step t: down, mid = ControlNet(x, t, embeds, cond, cond_scale)
//               eps = UNet(cat(x, prev), t, embeds, down, mid)
//               [guidance > 1: eps = eps_u + g * (eps_c - eps_u)]
//               x = scheduler.step(eps, t, x)
//   image = (vae.decode(x / sf) / 2 + 0.5).clamp(0, 1); uint8 = round(x*255)
//   (round half to even, numpy's rule).
//
// Step-level batching: Begin() prepares per-item FrameStates, Step() advances
// any set of states by one denoising step in as few network calls as
// possible (items may be at different steps), Finish() decodes. Render() =
// Begin + Step until all finished + Finish.
//
// Work that does not change between the steps of a frame is done once
// (docs/BENCHMARKS.md, "Step-invariant work"): the ControlNet's condition
// embedding in Begin (per item), the two networks' time embeddings once per
// timestep value (TimeEmbeddingCache), the cross-attention keys and values
// of each prompt once per layer (PromptKvCache), and a group of one item
// skips the per-step concatenations. These caches live with the pipeline:
// the environment's weights must not change while a FramePipeline exists. The arithmetic is the
// forward's own, so a batch-1 step is bitwise what ControlNet/UNet Run would give.
//
// Departures from the reference (documented choices):
//  * Random numbers: per item, two torch CPU generators
//    at::make_generator<at::CPUGeneratorImpl>(seed) (vae_noise_seed for the
//    latent_dist.sample() noise, init_noise_seed for x_T), each drawing one
//    [1, 4, h, w] float32 tensor on the CPU, so an item's numbers do not
//    depend on what else is in the batch or on the device. The reference
//    draws the VAE noise from torch's GLOBAL generator and x_T from the
//    pipeline generator; with global seed = vae_noise_seed and generator seed
//    = init_noise_seed the tensors are the same (fd_pipeline README, Random
//    numbers). Tests inject the reference's tensors instead.
//  * No resizing: inputs must already have the frame size (the GUI resizes
//    to 512x512 with bilinear/LANCZOS); sizes must be multiples of 8.
//  * The ControlLoRA scale is the environment's (a property of the loaded
//    UNet), not per item; the ControlNet conditioning scale and guidance are
//    per item (items with different values run in separate network calls).
//  * Latents and the scheduler run in float32 whatever the model dtype; the
//    networks get their inputs cast to the model dtype (diffusers keeps
//    latents in the model dtype and upcasts only inside step()).
//  * guidance > 1: diffusers batches [uncond, cond] rows; here the
//    unconditional row uses the environment's negative_prompt_embeds and the
//    same condition and prev latent (pipeline.py duplicates both).
//  * "G-buffer only" start (no previous frame): black irradiance and a zero
//    previous latent (no VAE encode), as the authors' stage-1 training's
//    --use_black_irradiance; no reference output exists for it.
//
// Thread-safety: a FramePipeline is immutable after construction; Begin /
// Step / Finish / Render may be called from several threads with disjoint
// FrameStates (the networks only read their weights).
#ifndef FD_MODEL_PIPELINE_FRAME_PIPELINE_H_
#define FD_MODEL_PIPELINE_FRAME_PIPELINE_H_

#include <torch/types.h>

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/types/span.h"
#include "model/networks/prompt_kv_cache.h"
#include "model/pipeline/conditioning.h"
#include "model/pipeline/environment.h"
#include "model/pipeline/time_embedding_cache.h"
#include "model/runtime/core_budget.h"
#include "model/schedulers/scheduler.h"

namespace fd::model {

// One frame to render. Images are HWC ([H, W, C], or [H, W] for one channel)
// on any device, uint8 (0..255) or floating point in [0, 1].
struct PipelineInput {
  // The previous output frame, or the keyframe ([H, W, 3]); undefined = the
  // "G-buffer only" start (black irradiance, zero previous latent). A float
  // frame is VAE-encoded as given (x*2-1, no quantisation); the irradiance
  // quantises it like the reference's PIL image.
  torch::Tensor previous_frame;
  // The previous frame's RAW (not sky filled) basecolor [H, W, 3]; required
  // with previous_frame (for the keyframe: the keyframe's own basecolor).
  torch::Tensor previous_basecolor;

  // The G-buffer of the frame to render.
  torch::Tensor basecolor;  // [H, W, 3]
  torch::Tensor normals;    // [H, W, 3]
  torch::Tensor depth;      // [H, W] or [H, W, 1]
  torch::Tensor roughness;  // [H, W] or [H, W, 1]
  torch::Tensor metallic;   // [H, W] or [H, W, 1]; undefined = zeros

  // Sky fill source; nullopt = the environment's sky mode.
  std::optional<SkyFillMode> sky_mode;
  torch::Tensor sky_image;  // [H, W, 3], required for kSkyImage

  // Seeds of the two noise draws (see the header comment).
  uint64_t vae_noise_seed = 0;
  uint64_t init_noise_seed = 0;
  // Injection (parity tests): given tensors [1, 4, h, w] replace the draws.
  torch::Tensor vae_sample_noise;
  torch::Tensor init_noise;

  // Lower-level entry: a ready ControlNet condition [1, 10, H, W] (skips the
  // G-buffer preprocessing; the G-buffer fields must then be empty) and/or a
  // ready (scaled) previous latent [1, 4, h, w] (skips the VAE encode). With
  // previous_frame also given, the latent replaces only its encode: the
  // frame still gives the irradiance and the sky fill (an environment's
  // "previous_latent": "reuse", with FrameOutput::latent of that frame).
  torch::Tensor condition;
  torch::Tensor prev_latent;
  // Overrides the environment's prompt embeddings: [1, T, D].
  torch::Tensor prompt_embeds;

  // 0 / nullopt = the environment's defaults.
  int steps = 0;
  std::optional<SchedulerType> scheduler;
  std::optional<double> guidance_scale;
  std::optional<double> conditioning_scale;

  // Also return the float image.
  bool want_float = false;
  // Keep what only inspection needs in the FrameState (condition,
  // irradiance, irradiance_u8, basecolor, noise_pred): validation renders,
  // tools and tests. Off, a state holds only what its steps need.
  bool keep_intermediates = false;
};

struct PipelineTimings {
  double encode_ms = 0;   // conditioning + VAE encode + noise (Begin)
  double denoise_ms = 0;  // sum of the batched steps this item took part in
  double decode_ms = 0;   // VAE decode + postprocess (Finish)
  int vae_threads = 0;    // intra-op threads of the decode (vae_on_free_core)
  int steps_beside = 0;   // steps whose ControlNet ran beside the UNet (ControlNetBeside)
};

// An item between Begin and Finish. Ownership: a value owned by the caller
// (the session layer); not thread-safe.
struct FrameState {
  int64_t height = 0;
  int64_t width = 0;
  SchedulerType scheduler_type = SchedulerType::kUniPCMultistep;
  const Scheduler* scheduler = nullptr;  // owned by the environment
  SchedulerState scheduler_state;
  double guidance_scale = 1.0;
  double conditioning_scale = 1.0;
  bool want_float = false;

  // The ControlNet's condition embedding (controlnet_cond_embedding of the
  // condition), computed once in Begin instead of at every step:
  // [1, C0, h, w], model dtype and device.
  torch::Tensor condition_embedding;
  // [1, 4, h, w] float32 (scaled); with basecolor patches the UNet's whole
  // extra input [1, 4 + 3 f^2, h, w] (the patches after the latent).
  torch::Tensor prev_latent;
  torch::Tensor latents;          // [1, 4, h, w] float32, current x_t
  torch::Tensor prompt_embeds;    // [1, T, D]
  torch::Tensor negative_embeds;  // [1, T, D] when guidance > 1
  // Only with PipelineInput::keep_intermediates:
  torch::Tensor condition;  // [1, 10, H, W] float32, model device
  // what the conditioning computed (undefined for a ready condition):
  torch::Tensor irradiance;     // float32 [1, 1, H, W]
  torch::Tensor irradiance_u8;  // uint8 [1, 1, H, W]
  torch::Tensor basecolor;      // uint8 [1, 3, H, W] after the sky fill
  torch::Tensor noise_pred;     // [1, 4, h, w] of the last step
  bool keep_intermediates = false;
  PipelineTimings timings;

  bool finished() const { return scheduler_state.finished(); }
  int step_index() const { return scheduler_state.step_index(); }
};

struct FrameOutput {
  torch::Tensor image_uint8;  // [H, W, 3] uint8 (CPU)
  torch::Tensor image_float;  // [1, 3, H, W] float32 in [0, 1] (CPU), if asked
  torch::Tensor decoded;      // [1, 3, H, W] float32 raw decoder output, if asked
  // The denoised latent the image was decoded from, [1, 4, h, w] float32
  // (scaled, as PipelineInput::prev_latent takes it), on the model's device.
  torch::Tensor latent;
  PipelineTimings timings;
};

// How Finish runs the VAE decoder over several finished states.
enum class VaeDecodeBatching {
  // Batched on CUDA (one decoder call per frame size: 1257 of a frame's
  // ~7270 GMAC at SD1.5 shapes, worth batching); on the CPU batched when the
  // calling thread runs more than one intra-op thread (a batched decode then
  // gave 1.05-1.45x the items/s of per-item calls at config B and the small
  // preset) and per item at one thread (where batching gained nothing:
  // 0.96-1.02x; docs/BENCHMARKS.md, "Batched VAE") or with batch_invariant
  // (a batched decode is not bitwise the per-item one on the CPU).
  kAuto,
  kPerItem,
  kBatched,  // one call per frame size (latent height x width)
};

// Step can run the UNet's down path (conv_in, down and mid blocks) on the
// calling thread's companion thread (model/runtime/companion_thread.h) while
// the calling thread runs the ControlNet, which the down path does not need;
// the up path then adds the ControlNet's residuals. A second core used
// without splitting operators: every operator runs as in the sequential
// step, so the result is bitwise the same whichever way a step runs (so a
// step may choose per call). CPU only; ChooseIntraOpThreads measures whether
// it pays. Unless kNever, Finish of a 1-thread pipeline also hands every
// second per-item decode to the companion while a core is free (bitwise too).
enum class ControlNetBeside {
  kNever,
  kAlways,
  // Only when a core is free in the core budget as the step starts (a lone
  // session on a server whose other workers idle), else sequential.
  kWhenCoreFree,
};

struct FramePipelineOptions {
  VaeDecodeBatching vae_decode = VaeDecodeBatching::kAuto;
  // Step and Finish run their convolutions and linear layers sample by
  // sample (model/runtime/batch_invariance.h), so a frame's result is bitwise the
  // same whatever it is batched with (Begin is per item anyway).
  bool batch_invariant = false;
  // LibTorch intra-op threads for Begin, Step and Finish (set on the calling
  // thread for the call, then restored); 0 = the calling thread's own count.
  // ChooseIntraOpThreads (thread_choice.h) measures which count is fastest
  // for an environment. Fixed for the pipeline's life: at the project's
  // shapes a frame measured bitwise the same at one and two threads, but a
  // kernel may round differently at another count.
  int intra_op_threads = 0;
  // Whether Step runs the ControlNet beside the UNet (ControlNetBeside).
  ControlNetBeside controlnet_beside_unet = ControlNetBeside::kNever;
  // Begin (the VAE encode) and Finish (the VAE decode) of a pipeline at one
  // intra-op thread run at two while the core budget has a core free (a
  // lone session on a 2-core server: the street decode took 38 ms at two
  // threads against 69 at one). CPU only. The frames are bitwise the
  // one-thread frames at the project's shapes (the VAE's channels-last
  // GroupNorm is model/runtime/group_norm_kernel.h, and oneDNN's forward
  // convolutions measured invariant; HoistedStepTest.FramesAreTheSameAt*),
  // but that is measured rather than promised by oneDNN, so batch_invariant,
  // which promises it, ignores this option. Such a decode runs per item
  // (VaeDecodeBatching aside).
  bool vae_on_free_core = false;
  // The cores Begin, Step and Finish claim while they compute, and where
  // kWhenCoreFree looks for a free one; nullptr = CoreBudget::Process().
  // Must outlive the pipeline.
  CoreBudget* core_budget = nullptr;
};

class FramePipeline {
 public:
  // `environment` must stay loaded (shared ownership).
  explicit FramePipeline(std::shared_ptr<const Environment> environment,
                         FramePipelineOptions options = {});

  const Environment& environment() const { return *env_; }

  // Validates and prepares every item (conditioning, VAE encode of the
  // previous frame, noise, scheduler state). Items are prepared one by one
  // (the VAE encode is not batched: simple, and exactly batch independent).
  // Errors: INVALID_ARGUMENT "item i: <field> ..." (missing/extra inputs,
  // wrong rank or channel count, mismatched sizes, sizes not multiples of 8,
  // NaN/Inf, values outside [0, 1], bad noise shapes, steps < 1, guidance
  // < 1, prompt embeddings of the wrong width); FAILED_PRECONDITION when no
  // prompt embeddings or (guidance > 1) negative embeddings are available;
  // NOT_FOUND for a scheduler the environment lacks; INTERNAL on torch errors.
  absl::StatusOr<std::vector<FrameState>> Begin(absl::Span<const PipelineInput> items) const;

  // One denoising step for every given state (each at its own step index).
  // States with the same size, scheduler, prompt length, guidance and
  // conditioning scale share one ControlNet + UNet call. Errors:
  // INVALID_ARGUMENT (null or duplicate state), FAILED_PRECONDITION (a
  // finished state), INTERNAL. On error, states may have been partly
  // advanced only for INTERNAL.
  absl::Status Step(absl::Span<FrameState* const> states) const;

  // Decodes finished states, batched per frame size or per item (see
  // VaeDecodeBatching). FAILED_PRECONDITION for an unfinished state;
  // INTERNAL on torch errors.
  absl::StatusOr<std::vector<FrameOutput>> Finish(absl::Span<FrameState* const> states) const;

  // Begin + Step until all are finished + Finish.
  absl::StatusOr<std::vector<FrameOutput>> Render(absl::Span<const PipelineInput> items) const;

 private:
  // Whether Finish decodes a group of states in one call (VaeDecodeBatching,
  // resolved for the calling thread).
  bool BatchDecode() const;
  // The cores a call on the calling thread computes on, claimed for its
  // duration.
  CoreBudget::Claim ClaimCores() const;
  // For Begin and Finish: a free core's claim when vae_on_free_core applies
  // and one is free (the call then runs at intra-op threads + 1).
  std::optional<CoreBudget::Claim> ClaimFreeCoreForVae() const;

  std::shared_ptr<const Environment> env_;
  VaeDecodeBatching vae_decode_ = VaeDecodeBatching::kAuto;
  bool batch_invariant_ = false;
  // Shared by copies of this pipeline (same environment).
  std::shared_ptr<TimeEmbeddingCache> time_embeddings_;
  std::shared_ptr<PromptKvCache> prompt_kv_;
  int intra_op_threads_ = 0;
  ControlNetBeside controlnet_beside_unet_ = ControlNetBeside::kNever;
  bool vae_on_free_core_ = false;
  CoreBudget* core_budget_;
};

}  // namespace fd::model

#endif  // FD_MODEL_PIPELINE_FRAME_PIPELINE_H_

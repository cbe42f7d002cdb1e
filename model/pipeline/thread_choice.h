// ChooseIntraOpThreads: measures, once per environment, whether a frame's
// denoising steps run faster at one LibTorch intra-op thread or at up to
// `max_threads`, so that giving a worker more threads never makes its frames
// slower (docs/BENCHMARKS.md, "Threading policy").
//
// Why measure: whether a second thread helps depends on the work per kernel.
// On 2 cores the golden config-B frame (latent 12x16) took 210 ms at one
// thread and 274 ms at two, while the `small` preset's VAE decode (32x32
// latent) ran 1.8x faster at two; no fixed size threshold holds across
// machines. The answer is used as FramePipelineOptions::intra_op_threads,
// fixed for the pipeline's life, so that numerics do not change between
// frames.
#ifndef FD_MODEL_PIPELINE_THREAD_CHOICE_H_
#define FD_MODEL_PIPELINE_THREAD_CHOICE_H_

#include <memory>

#include "absl/status/statusor.h"
#include "model/pipeline/environment.h"
#include "model/pipeline/frame_pipeline.h"

namespace fd::model {

// A frame of random uint8 images drawn from `seed` (in this order: previous
// frame, previous basecolor, basecolor, normals, depth, roughness,
// metallic), sky mode previous_output, everything else the environment's
// defaults: what the calibration times, and what benchmarks render.
PipelineInput RandomGBufferFrame(int64_t height, int64_t width, uint64_t seed);

struct ThreadChoice {
  int threads = 1;                      // the intra-op count to use
  bool controlnet_beside_unet = false;  // the companion pays (ControlNetBeside)
  double step_ms_one = 0;               // median step at 1 thread
  double step_ms_many = 0;              // median step at max_threads (0 if not timed)
  double step_ms_beside = 0;  // median step at 1 thread, ControlNet beside the UNet (0: not timed)
  // Whether whole frames ran faster with a second thread for the VAE
  // (FramePipelineOptions::vae_on_free_core; timed when the companion is
  // timed and 1 thread was chosen), and their medians without and with it
  // (ms; 0: not timed).
  bool vae_on_free_core = false;
  double frame_ms_vae_one = 0;
  double frame_ms_vae_two = 0;
};

struct ThreadChoiceOptions {
  int rounds = 3;
  // The frame size timed; 0 = the environment's own (settings width/height).
  int64_t width = 0;
  int64_t height = 0;
  // Also time the ControlNet beside the UNet on a companion thread (only
  // where the process has at least 2 cores: CoreBudget::Process()).
  bool companion = true;
};

// Times `rounds` single denoising steps (batch 1, the environment's own
// frame size and sampler, a random G-buffer, guidance 1) at 1 thread, at
// `max_threads` (if > 1), and at 1 thread with the ControlNet beside the
// UNet on a companion thread (the second core used by whole sub-networks;
// see ThreadChoiceOptions::companion), alternating, after one untimed step
// of each; picks the one with the lowest median. When 1 thread is picked
// and the companion was timed, also times `rounds` whole frames without and
// with vae_on_free_core. With nothing to compare (or on a non-CPU device)
// returns 1 thread without timing. The calling thread's own count is
// restored. Errors: INTERNAL (torch), or what FramePipeline reports.
// Thread-safety: as FramePipeline (the environment is only read).
absl::StatusOr<ThreadChoice> ChooseIntraOpThreads(std::shared_ptr<const Environment> environment,
                                                  int max_threads,
                                                  const ThreadChoiceOptions& options = {});

}  // namespace fd::model

#endif  // FD_MODEL_PIPELINE_THREAD_CHOICE_H_

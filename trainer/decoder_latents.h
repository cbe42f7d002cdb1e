// The latents of the decoder fine-tune on the model's own frames
// (framediffuser-train decoder --decoder_latents_from ENV): ENV, a finished
// environment, renders autoregressive chains of training frames through the
// server's FramePipeline at its own serving settings (environment.json's
// steps, scheduler, conditioning scale and "previous_latent"; sky pixels
// filled from the frame's ground truth, as scripts/evaluate.sh's client sends
// them), each chain from a ground-truth keyframe as a client starts one. Every rendered
// frame's denoised latent is kept with the position of the ground truth it
// should decode to. Why: a one-step frame is the denoiser's mean estimate, a
// latent the encoder never produces, and a decoder trained only on the
// encoder's latents decodes it as it would a sharp frame's
// (docs/EVALUATION.md, "Tried in a thirteenth round").
//
// Thread-safety: none needed; the environment's networks are only read.
#ifndef FD_TRAINER_DECODER_LATENTS_H_
#define FD_TRAINER_DECODER_LATENTS_H_

#include <torch/types.h>

#include <cstdint>
#include <memory>
#include <vector>

#include "absl/status/statusor.h"
#include "model/pipeline/environment.h"
#include "trainer/training_data.h"

namespace fd::trainer {

struct DecoderLatent {
  int sequence = 0;      // index into TrainingData::sequences
  int64_t position = 0;  // the frame the latent was rendered for
  torch::Tensor latent;  // [C, h, w] float32 on the CPU, scaled (FrameOutput::latent)
};

struct DecoderLatentOptions {
  int chains = 64;        // chains rendered, each from its own keyframe
  int chain_frames = 16;  // frames rendered after each keyframe (fewer where a sequence ends)
  uint64_t seed = 0;      // chain starts and noise (MixSeed streams)
};

struct DecoderLatentSet {
  std::vector<DecoderLatent> latents;
  double mean_psnr = 0;  // of the rendered frames against the ground truth (uint8), dB
};

// Renders the chains. Starts are drawn per chain: a sequence with
// probability proportional to its frames, then a keyframe position that
// leaves room for chain_frames frames where the sequence allows it.
// Errors: INVALID_ARGUMENT (chains or chain_frames < 1, no sequence with two
// frames, a resolution other than the environment's); the pipeline's errors.
absl::StatusOr<DecoderLatentSet> RenderDecoderLatents(
    const std::shared_ptr<const fd::model::Environment>& environment, const TrainingData& data,
    const DecoderLatentOptions& options);

}  // namespace fd::trainer

#endif  // FD_TRAINER_DECODER_LATENTS_H_

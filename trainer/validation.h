// Validation during training: an autoregressive render of a held-out
// sequence with the current weights through the server's own FramePipeline
// (the first frame's ground truth is the keyframe, every later frame is
// conditioned on the previous output, as in deployment), PSNR / SSIM per
// frame against the ground truth (fd::client_io's metrics), and a contact sheet:
// one row per shown frame, columns GT | ours | basecolor | irradiance.
//
// Thread-safety: none needed; the environment's networks are only read.
#ifndef FD_TRAINER_VALIDATION_H_
#define FD_TRAINER_VALIDATION_H_

#include <torch/types.h>

#include <cstdint>
#include <memory>
#include <vector>

#include "absl/status/statusor.h"
#include "client_sdk/image.h"
#include "model/pipeline/environment.h"
#include "model/pipeline/frame_pipeline.h"
#include "trainer/training_data.h"

namespace fd::trainer {

struct ValidationFrame {
  int64_t frame_number = 0;
  double psnr = 0;
  double ssim = 0;
};

struct ValidationResult {
  std::vector<ValidationFrame> frames;  // the rendered frames (not the keyframe)
  double mean_psnr = 0;
  double mean_ssim = 0;
  std::vector<torch::Tensor> rendered;  // uint8 [H, W, 3] per rendered frame
  fd::client::Image8 contact_sheet;
};

// Renders frames 1 .. min(frames, T - 1) of `seq` (frame 0 = keyframe) with
// the environment's scheduler and steps; sky pixels are filled from each
// frame's ground truth (the sky injection the trainer uses). Noise seeds
// are the frame positions, so the same weights give the same frames.
// Errors: INVALID_ARGUMENT (fewer than 2 frames, frames < 1), the
// pipeline's errors.
absl::StatusOr<ValidationResult> RenderValidation(
    const std::shared_ptr<const fd::model::Environment>& environment, const TrainingSequence& seq,
    int frames);

// The FramePipeline request of frame `position` conditioned on `previous`
// (uint8 [3, H, W]) showing frame `previous_position`, with GT sky fill.
// Shared by the validation render and stage 3's generation.
struct FrameRequestInputs {
  const TrainingSequence* seq = nullptr;
  int64_t position = 0;
  torch::Tensor previous;  // uint8 [3, H, W]
  int64_t previous_position = 0;
  uint64_t seed = 0;
};
fd::model::PipelineInput MakeFrameRequest(const FrameRequestInputs& inputs);

// A uint8 [H, W, C] tensor as fd::client's float image in [0, 1] (what its
// metrics take).
fd::client::ImageF ToImageF(const torch::Tensor& hwc_u8);

}  // namespace fd::trainer

#endif  // FD_TRAINER_VALIDATION_H_

// One-step denoising quality of an environment, per timestep: the held-out
// ground truth is encoded, noised to timestep t (DDPMScheduler.add_noise),
// and the ControlNet + UNet predict the noise once, with the frame's own
// G-buffer and the ground-truth previous frame (teacher forcing). From that
// prediction the clean latent x0 = (x_t - sqrt(1 - a_t) eps) / sqrt(a_t) is
// decoded and compared with the autoencoder's round trip of the ground truth.
//
// It separates the denoiser from the sampler and from drift: a model whose
// x0 estimate at mid timesteps already lacks the frame's layout has not
// learned to follow its condition, whatever the sampler does; one whose
// estimate is good but whose sampled frames are not points at the sampler
// or at the autoregressive loop.
#ifndef FD_TOOLS_EVALUATE_DENOISING_H_
#define FD_TOOLS_EVALUATE_DENOISING_H_

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"

namespace fd::evaluate {

struct DenoisingOptions {
  std::string env_dir;   // an environment folder (model/pipeline/environment.h)
  std::string sequence;  // a held-out sequence with FinalImage (dataset layout)
  int frames = 8;        // evenly spaced frames (each needs the one before it)
  std::vector<int> timesteps = {100, 300, 500, 700, 900};
  uint64_t seed = 0;  // the added noise
  std::string sheet;  // optional PNG: per frame, round trip | x0 at each t
};

// One text line per timestep (noise MSE, x0 PSNR against the round trip and
// against the ground truth, means over the frames). Errors: NOT_FOUND /
// INVALID_ARGUMENT from the environment or the sequence (fewer than 2
// frames, a timestep outside [0, num_train_timesteps)), INTERNAL.
absl::StatusOr<std::string> DescribeDenoising(const DenoisingOptions& options);

}  // namespace fd::evaluate

#endif  // FD_TOOLS_EVALUATE_DENOISING_H_

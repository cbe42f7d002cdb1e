// Image conversions and contact-sheet pasting shared by the evaluation
// commands (evaluation.cc, denoising.cc).
#ifndef FD_TOOLS_EVALUATE_IMAGE_HELPERS_H_
#define FD_TOOLS_EVALUATE_IMAGE_HELPERS_H_

#include <torch/types.h>

#include <vector>

#include "client_sdk/image.h"

namespace fd::evaluate {

// uint8 -> float [0, 1], same size and channels.
fd::client::ImageF ToUnitFloat(const fd::client::Image8& image);

// Decoded VAE output [N, 3, H, W] in ~[-1, 1] (CPU float) -> N uint8 RGB
// images: the pipeline's postprocess (model/pipeline/frame_pipeline.cc).
std::vector<fd::client::Image8> DecodedToImages(const torch::Tensor& decoded);

// Copies `panel` (RGB or gray) into the RGB `sheet` at (x0, y0).
void Blit(const fd::client::Image8& panel, fd::client::Image8* sheet, int x0, int y0);

}  // namespace fd::evaluate

#endif  // FD_TOOLS_EVALUATE_IMAGE_HELPERS_H_

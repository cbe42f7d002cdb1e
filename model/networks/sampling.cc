// Ports of diffusers v0.31.0 Downsample2D (downsampling.py) and Upsample2D
// (upsampling.py); see sampling.h.
#include "model/networks/sampling.h"

#include <torch/torch.h>

namespace fd::model {

Downsample2DImpl::Downsample2DImpl(int64_t channels, int64_t out_channels, int64_t padding)
    : padding_(padding) {
  conv = register_module("conv", LoraConv2d(channels, out_channels, 3, 2, padding));
}

torch::Tensor Downsample2DImpl::forward(const torch::Tensor& x) {
  // x: [N, C, H, W]
  if (padding_ == 0) {
    // F.pad(x, (0, 1, 0, 1)): one zero column right, one zero row bottom.
    return conv(torch::constant_pad_nd(x, {0, 1, 0, 1}, 0));
  }
  return conv(x);
}

Upsample2DImpl::Upsample2DImpl(int64_t channels, int64_t out_channels) {
  conv = register_module("conv", LoraConv2d(channels, out_channels, 3, 1, 1));
}

torch::Tensor Upsample2DImpl::forward(const torch::Tensor& x,
                                      const std::vector<int64_t>& output_size) {
  // x: [N, C, H, W]
  const torch::ScalarType dtype = x.scalar_type();
  torch::Tensor h = dtype == torch::kBFloat16 ? x.to(torch::kFloat32) : x;
  if (h.size(0) >= 64) h = h.contiguous();
  if (output_size.empty()) {
    // F.interpolate(scale_factor=2.0, mode="nearest")
    h = torch::upsample_nearest2d(h, {2 * h.size(2), 2 * h.size(3)}, 2.0, 2.0);
  } else {
    // F.interpolate(size=output_size, mode="nearest")
    h = torch::upsample_nearest2d(h, output_size);
  }
  if (dtype == torch::kBFloat16) h = h.to(dtype);
  return conv(h);  // [N, out, H', W']
}

}  // namespace fd::model

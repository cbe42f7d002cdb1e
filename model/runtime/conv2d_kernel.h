// The channels-last layout that makes oneDNN fast on full-resolution images,
// and the CPU convolution kernel for tensors in it.
//
// LibTorch 1.13 runs a float32 CPU convolution in oneDNN (mkldnn_convolution)
// when its input is large, and oneDNN given NCHW tensors reorders them into
// its blocked layout and back on every call. With channels-last (NHWC)
// tensors it works in place. That matters at full resolution with few
// channels: the VAE's outer levels and the ControlNet's G-buffer encoder
// (street's 128x128 frame, medians of 3 interleaved rounds: decode 77 -> 58
// ms, encode + conditioning 40 -> 33 ms; docs/BENCHMARKS.md, "Channels-last
// VAE and G-buffer encoder"). At the latent sizes of the UNet and ControlNet trunks it gains
// nothing measurable, and in training (autograd) it was not faster either,
// so only inference converts.
//
// ATen's kernel heuristic (ConvParams::use_mkldnn) sends a single-threaded
// 1x1 convolution to the im2col kernel, which on a channels-last input of
// [1, 64, 128, 128] takes 0.85 ms against oneDNN's 0.41; Conv2dForward calls
// oneDNN directly for channels-last inputs.
#ifndef FD_MODEL_RUNTIME_CONV2D_KERNEL_H_
#define FD_MODEL_RUNTIME_CONV2D_KERNEL_H_

#include <torch/types.h>

#include <cstdint>

namespace fd::model {

// conv2d(x, weight, bias, stride, padding) (dilation 1, groups 1), equal to
// at::conv2d within float32 rounding (bitwise for NCHW inputs, which take
// at::conv2d itself). A channels-last float32 CPU input outside autograd runs
// oneDNN directly; the output keeps the input's memory format. `bias` may be
// undefined. Throws like at::conv2d. Thread-safe.
torch::Tensor Conv2dForward(const torch::Tensor& x, const torch::Tensor& weight,
                            const torch::Tensor& bias, int64_t stride, int64_t padding);

// Whether a network should run `x` in channels-last memory format: a 4-D CPU
// float32 tensor with grad mode off (inference) and oneDNN available. The
// networks that gain (the VAE, the ControlNet's G-buffer encoder) convert
// their input with ToChannelsLastForInference and return NCHW-contiguous
// outputs, so callers never see the layout.
bool UseChannelsLast(const torch::Tensor& x);

// x in channels-last memory format where UseChannelsLast(x), else x itself.
torch::Tensor ToChannelsLastForInference(const torch::Tensor& x);

}  // namespace fd::model

#endif  // FD_MODEL_RUNTIME_CONV2D_KERNEL_H_

// See group_norm_kernel.h for why GroupNorm has its own kernel here.
#include "model/runtime/group_norm_kernel.h"

#include <ATen/Parallel.h>
#include <c10/util/Exception.h>
#include <torch/torch.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

namespace fd::model {
namespace {

// Rows (spatial positions, C floats each) per partial sum. Fixed, so that
// the blocks do not depend on the thread count; small enough that a frame's
// outer level ([1, 32, 128, 128]: 64 blocks) still spreads over the threads.
constexpr int64_t kRowsPerBlock = 256;

// Four floats in one SSE register (GCC/Clang vector extension, the x86-64
// baseline, so no per-instruction-set build); unaligned loads and stores go
// through memcpy.
typedef float Float4 __attribute__((vector_size(16)));

inline Float4 Load4(const float* p) {
  Float4 v;
  std::memcpy(&v, p, sizeof(v));
  return v;
}

inline void Store4(float* p, Float4 v) { std::memcpy(p, &v, sizeof(v)); }

// Channels per register tile: 16 channels' sums and squares (or scales and
// shifts) stay in registers while a block's rows stream past.
constexpr int64_t kTile = 16;
constexpr int64_t kTileVectors = kTile / 4;

// Per-channel sum and sum of squares of rows [begin, end) of one item:
// out[0..C) the sums, out[C..2C) the squares. Float within a block, which is
// as exact as LibTorch's float accumulation over the whole map; the blocks
// are added in double.
void SumRows(const float* x, int64_t channels, int64_t begin, int64_t end, float* out) {
  int64_t c0 = 0;
  for (; c0 + kTile <= channels; c0 += kTile) {
    Float4 sum[kTileVectors] = {};
    Float4 squares[kTileVectors] = {};
    for (int64_t r = begin; r < end; ++r) {
      const float* row = x + r * channels + c0;
      for (int64_t k = 0; k < kTileVectors; ++k) {
        const Float4 v = Load4(row + 4 * k);
        sum[k] += v;
        squares[k] += v * v;
      }
    }
    for (int64_t k = 0; k < kTileVectors; ++k) {
      Store4(out + c0 + 4 * k, sum[k]);
      Store4(out + channels + c0 + 4 * k, squares[k]);
    }
  }
  for (int64_t c = c0; c < channels; ++c) {  // channels past the last tile
    float sum = 0.0f;
    float squares = 0.0f;
    for (int64_t r = begin; r < end; ++r) {
      const float v = x[r * channels + c];
      sum += v;
      squares += v * v;
    }
    out[c] = sum;
    out[channels + c] = squares;
  }
}

// y = x * scale + shift per channel for rows [begin, end) of one item.
void ApplyRows(const float* x, const float* scale, const float* shift, int64_t channels,
               int64_t begin, int64_t end, float* y) {
  int64_t c0 = 0;
  for (; c0 + kTile <= channels; c0 += kTile) {
    Float4 s[kTileVectors];
    Float4 b[kTileVectors];
    for (int64_t k = 0; k < kTileVectors; ++k) {
      s[k] = Load4(scale + c0 + 4 * k);
      b[k] = Load4(shift + c0 + 4 * k);
    }
    for (int64_t r = begin; r < end; ++r) {
      const float* row = x + r * channels + c0;
      float* dst = y + r * channels + c0;
      for (int64_t k = 0; k < kTileVectors; ++k)
        Store4(dst + 4 * k, Load4(row + 4 * k) * s[k] + b[k]);
    }
  }
  for (int64_t r = begin; r < end; ++r) {
    for (int64_t c = c0; c < channels; ++c) {
      y[r * channels + c] = x[r * channels + c] * scale[c] + shift[c];
    }
  }
}

}  // namespace

bool UseInvariantGroupNorm(const torch::Tensor& x) {
  return x.defined() && x.dim() == 4 && x.is_cpu() && x.scalar_type() == torch::kFloat32 &&
         x.is_contiguous(at::MemoryFormat::ChannelsLast) && !x.is_contiguous() &&
         !(torch::GradMode::is_enabled() && x.requires_grad());
}

torch::Tensor GroupNormForward(const torch::nn::GroupNormImpl& norm, const torch::Tensor& x) {
  const torch::nn::GroupNormOptions& options = norm.options;
  const torch::Tensor& weight = norm.weight;
  const torch::Tensor& bias = norm.bias;
  const bool affine_needs_grad =
      torch::GradMode::is_enabled() &&
      ((weight.defined() && weight.requires_grad()) || (bias.defined() && bias.requires_grad()));
  if (!UseInvariantGroupNorm(x) || affine_needs_grad) {
    return torch::group_norm(x, options.num_groups(), weight, bias, options.eps());
  }
  // x: [N, C, H, W] stored as [N, H*W, C]
  const int64_t n = x.size(0);
  const int64_t channels = x.size(1);
  const int64_t groups = options.num_groups();
  TORCH_CHECK(channels == options.num_channels(), "GroupNorm expected ", options.num_channels(),
              " channels, got ", channels);
  TORCH_CHECK(groups > 0 && channels % groups == 0, "GroupNorm: ", channels,
              " channels do not split into ", groups, " groups");
  const int64_t rows = x.size(2) * x.size(3);
  const int64_t per_group = channels / groups;
  const int64_t blocks = std::max<int64_t>(1, (rows + kRowsPerBlock - 1) / kRowsPerBlock);
  const float* in = x.data_ptr<float>();

  // Pass 1: partial sums of fixed blocks, in parallel; each block's sums
  // are the same whichever thread computes it.
  std::vector<float> partial(static_cast<size_t>(n * blocks * 2 * channels));
  at::parallel_for(0, n * blocks, 1, [&](int64_t begin, int64_t end) {
    for (int64_t t = begin; t < end; ++t) {
      const int64_t item = t / blocks;
      const int64_t first = (t % blocks) * kRowsPerBlock;
      SumRows(in + item * rows * channels, channels, first, std::min(rows, first + kRowsPerBlock),
              partial.data() + t * 2 * channels);
    }
  });

  // Moments per (item, group), adding the blocks in order, and from them
  // each channel's scale and shift: y = x * scale + shift.
  const torch::Tensor gamma = weight.defined() ? weight.to(torch::kFloat32).contiguous() : weight;
  const torch::Tensor beta = bias.defined() ? bias.to(torch::kFloat32).contiguous() : bias;
  const float* gamma_data = gamma.defined() ? gamma.data_ptr<float>() : nullptr;
  const float* beta_data = beta.defined() ? beta.data_ptr<float>() : nullptr;
  std::vector<float> scale(static_cast<size_t>(n * channels));
  std::vector<float> shift(static_cast<size_t>(n * channels));
  const double count = static_cast<double>(rows * per_group);
  for (int64_t item = 0; item < n; ++item) {
    for (int64_t g = 0; g < groups; ++g) {
      double sum = 0.0;
      double squares = 0.0;
      for (int64_t b = 0; b < blocks; ++b) {
        const float* block = partial.data() + (item * blocks + b) * 2 * channels;
        for (int64_t c = g * per_group; c < (g + 1) * per_group; ++c) {
          sum += block[c];
          squares += block[channels + c];
        }
      }
      const double mean = sum / count;
      const double variance = std::max(squares / count - mean * mean, 0.0);
      const double rstd = 1.0 / std::sqrt(variance + options.eps());
      for (int64_t c = g * per_group; c < (g + 1) * per_group; ++c) {
        const double s = rstd * (gamma_data != nullptr ? gamma_data[c] : 1.0);
        scale[item * channels + c] = static_cast<float>(s);
        shift[item * channels + c] =
            static_cast<float>((beta_data != nullptr ? beta_data[c] : 0.0) - mean * s);
      }
    }
  }

  // Pass 2: elementwise, so any split of the rows gives the same values.
  torch::Tensor y = torch::empty_like(x, at::MemoryFormat::ChannelsLast);
  float* out = y.data_ptr<float>();
  at::parallel_for(0, n * blocks, 1, [&](int64_t begin, int64_t end) {
    for (int64_t t = begin; t < end; ++t) {
      const int64_t item = t / blocks;
      const int64_t first = (t % blocks) * kRowsPerBlock;
      ApplyRows(in + item * rows * channels, scale.data() + item * channels,
                shift.data() + item * channels, channels, first,
                std::min(rows, first + kRowsPerBlock), out + item * rows * channels);
    }
  });
  return y;  // [N, C, H, W], channels-last
}

}  // namespace fd::model

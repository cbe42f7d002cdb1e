// Conv2dForward and the channels-last inference layout
// (model/runtime/conv2d_kernel.h): which inputs take oneDNN directly, that
// every path equals at::conv2d (bitwise where it is at::conv2d itself,
// within float32 rounding otherwise), that autograd still flows, and that
// the networks which convert to channels-last hand back NCHW tensors equal
// to their NCHW forward.
#include "model/runtime/conv2d_kernel.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include "model/networks/vae.h"

namespace fd::model {
namespace {

constexpr auto kChannelsLast = at::MemoryFormat::ChannelsLast;

// Largest |a - b| relative to max |b| (the goldens' acceptance measure).
double RelativeError(const torch::Tensor& a, const torch::Tensor& b) {
  return (a - b).abs().max().item<double>() / b.abs().max().item<double>();
}

struct ConvCase {
  int64_t batch, in, out, size, kernel, stride, padding;
};

class Conv2dForwardTest : public ::testing::TestWithParam<ConvCase> {};

TEST_P(Conv2dForwardTest, ChannelsLastMatchesAtenAndNchwIsAtenItself) {
  const ConvCase c = GetParam();
  torch::manual_seed(3);
  const torch::Tensor x = torch::randn({c.batch, c.in, c.size, c.size});
  const torch::Tensor w = torch::randn({c.out, c.in, c.kernel, c.kernel}) * 0.1;
  const torch::Tensor b = torch::randn({c.out});
  torch::InferenceMode inference;
  const torch::Tensor reference = torch::conv2d(x, w, b, c.stride, c.padding);

  const torch::Tensor nchw = Conv2dForward(x, w, b, c.stride, c.padding);
  EXPECT_TRUE(nchw.equal(reference));
  EXPECT_TRUE(nchw.is_contiguous());

  const torch::Tensor nhwc = Conv2dForward(x.contiguous(kChannelsLast), w, b, c.stride, c.padding);
  EXPECT_TRUE(nhwc.is_contiguous(kChannelsLast));
  EXPECT_EQ(nhwc.sizes(), reference.sizes());
  EXPECT_LE(RelativeError(nhwc, reference), 1e-5);

  const torch::Tensor no_bias =
      Conv2dForward(x.contiguous(kChannelsLast), w, {}, c.stride, c.padding);
  EXPECT_LE(RelativeError(no_bias, torch::conv2d(x, w, {}, c.stride, c.padding)), 1e-5);
}

INSTANTIATE_TEST_SUITE_P(
    Shapes, Conv2dForwardTest,
    ::testing::Values(ConvCase{1, 32, 32, 128, 3, 1, 1},  // a VAE's outer level
                      ConvCase{2, 16, 32, 64, 3, 2, 1},   // G-buffer encoder, stride 2
                      ConvCase{1, 64, 32, 64, 1, 1, 0},   // resnet shortcut (1x1)
                      ConvCase{1, 3, 8, 16, 1, 1, 0},     // a 1x1 on a small input
                      ConvCase{2, 128, 128, 16, 3, 1, 1}));

TEST(Conv2dForwardAutogradTest, GoesThroughAtenAndGetsGradients) {
  torch::manual_seed(4);
  const torch::Tensor x = torch::randn({1, 8, 16, 16}).contiguous(kChannelsLast);
  const torch::Tensor w = (torch::randn({8, 8, 3, 3}) * 0.1).requires_grad_();
  const torch::Tensor y = Conv2dForward(x, w, {}, 1, 1);
  ASSERT_TRUE(y.requires_grad());
  y.sum().backward();
  ASSERT_TRUE(w.grad().defined());
  const torch::Tensor w2 = w.detach().clone().requires_grad_();
  torch::conv2d(x, w2, {}, 1, 1).sum().backward();
  EXPECT_LE(RelativeError(w.grad(), w2.grad()), 1e-5);
}

TEST(ChannelsLastTest, OnlyForFloatCpuTensorsOutsideAutograd) {
  const torch::Tensor x = torch::zeros({1, 3, 8, 8});
  {
    torch::InferenceMode inference;
    EXPECT_EQ(UseChannelsLast(x), at::hasMKLDNN());
    EXPECT_FALSE(UseChannelsLast(x.to(torch::kFloat64)));
    EXPECT_FALSE(UseChannelsLast(torch::zeros({3, 8, 8})));
    EXPECT_FALSE(UseChannelsLast(torch::Tensor()));
    if (at::hasMKLDNN()) {
      EXPECT_TRUE(ToChannelsLastForInference(x).is_contiguous(kChannelsLast));
    }
  }
  // Training keeps NCHW (grad mode on).
  EXPECT_FALSE(UseChannelsLast(x));
  EXPECT_TRUE(ToChannelsLastForInference(x).is_contiguous());
}

// The VAE converts to channels-last inside encode/decode at inference: its
// outputs are NCHW-contiguous and equal to the NCHW (grad-mode) forward.
TEST(ChannelsLastTest, VaeOutputsAreNchwAndEqualTheNchwForward) {
  AutoencoderKLConfig config;
  config.block_out_channels = {16, 32};
  config.down_block_types = {"DownEncoderBlock2D", "DownEncoderBlock2D"};
  config.up_block_types = {"UpDecoderBlock2D", "UpDecoderBlock2D"};
  config.layers_per_block = 1;
  config.norm_num_groups = 8;
  absl::StatusOr<AutoencoderKL> vae = MakeVae(config);
  ASSERT_TRUE(vae.ok()) << vae.status();
  torch::manual_seed(5);
  {
    torch::NoGradGuard no_grad;
    for (auto& p : (*vae)->parameters()) p.copy_(torch::randn(p.sizes()) * 0.1);
  }
  const torch::Tensor image = torch::rand({1, 3, 32, 32}) * 2 - 1;
  const torch::Tensor z = torch::randn({1, 4, 16, 16});

  // Grad mode on, nothing requiring grad: the NCHW path.
  DebugTaps training_taps;
  const torch::Tensor mean_nchw = (*vae)->encode(image).mean.detach();
  const torch::Tensor decoded_nchw = (*vae)->decode(z, &training_taps).detach();
  EXPECT_TRUE(training_taps.at("decoder.conv_in").is_contiguous());

  torch::InferenceMode inference;
  absl::StatusOr<LatentPosterior> posterior = (*vae)->Encode(image);
  ASSERT_TRUE(posterior.ok()) << posterior.status();
  DebugTaps taps;
  absl::StatusOr<torch::Tensor> decoded = (*vae)->Decode(z, &taps);
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  // Inside, the decoder ran channels-last (where oneDNN is built in).
  EXPECT_EQ(taps.at("decoder.conv_in").is_contiguous(kChannelsLast), at::hasMKLDNN());
  EXPECT_TRUE(posterior->moments.is_contiguous());
  EXPECT_TRUE(decoded->is_contiguous());
  EXPECT_LE(RelativeError(posterior->mean, mean_nchw), 1e-5);
  EXPECT_LE(RelativeError(*decoded, decoded_nchw), 1e-5);
}

}  // namespace
}  // namespace fd::model

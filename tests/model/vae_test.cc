// AutoencoderKL against the diffusers goldens (configs A and B): posterior
// moments/mean/logvar/std, the sampled and scaled previous-frame latent,
// decoding, and every debug activation of vae.safetensors.
#include "model/networks/vae.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <string>

#include "absl/strings/match.h"
#include "tests/model/network_golden.h"
#include "tests/testing/golden.h"

namespace fd::model {
namespace {

using testing::GoldenClose;
using testing::GoldenTensor;
using testing::ReadGolden;

class VaeGoldenTest : public ::testing::TestWithParam<std::string> {};

TEST_P(VaeGoldenTest, MatchesDiffusers) {
  const std::string config = GetParam();
  absl::StatusOr<AutoencoderKL> vae =
      LoadVae(fd::testing::GoldenPath(config + "/vae"), torch::kCPU, torch::kFloat32);
  ASSERT_TRUE(vae.ok()) << vae.status();
  const auto in = ReadGolden(config + "/golden/inputs.safetensors");
  const auto golden = ReadGolden(config + "/golden/vae.safetensors");
  const std::string tag = config + "/vae: ";
  const double scaling_factor = (*vae)->config().scaling_factor;

  // FrameDiffuser's prepare_lora_conditions: x = img * 2 - 1.
  DebugTaps taps;
  absl::StatusOr<LatentPosterior> posterior =
      (*vae)->Encode(GoldenTensor(in, "prev_image") * 2 - 1, &taps);
  ASSERT_TRUE(posterior.ok()) << posterior.status();
  EXPECT_TRUE(GoldenClose(tag + "posterior_moments", posterior->moments,
                          GoldenTensor(golden, "posterior_moments")));
  EXPECT_TRUE(
      GoldenClose(tag + "posterior_mean", posterior->mean, GoldenTensor(golden, "posterior_mean")));
  EXPECT_TRUE(GoldenClose(tag + "posterior_logvar", posterior->logvar,
                          GoldenTensor(golden, "posterior_logvar")));
  EXPECT_TRUE(
      GoldenClose(tag + "posterior_std", posterior->std, GoldenTensor(golden, "posterior_std")));
  torch::Tensor sample = posterior->Sample(GoldenTensor(in, "prev_image_noise"));
  EXPECT_TRUE(
      GoldenClose(tag + "posterior_sample", sample, GoldenTensor(golden, "posterior_sample")));
  EXPECT_TRUE(GoldenClose(tag + "prev_latent", sample * scaling_factor,
                          GoldenTensor(golden, "prev_latent")));

  torch::Tensor decode_input = GoldenTensor(in, "vae_decode_latents_scaled") / scaling_factor;
  EXPECT_TRUE(
      GoldenClose(tag + "decode_input", decode_input, GoldenTensor(golden, "decode_input")));
  absl::StatusOr<torch::Tensor> decoded = (*vae)->Decode(decode_input, &taps);
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  EXPECT_TRUE(GoldenClose(tag + "decoded", *decoded, GoldenTensor(golden, "decoded")));

  int debug_tensors = 0;
  for (const auto& [key, expected] : golden) {
    if (!absl::StartsWith(key, "debug.")) continue;
    ++debug_tensors;
    const std::string name = key.substr(6);
    ASSERT_TRUE(taps.count(name)) << "no activation recorded for " << key;
    EXPECT_TRUE(GoldenClose(tag + key, taps[name], expected));
  }
  EXPECT_GT(debug_tensors, 0);
}

INSTANTIATE_TEST_SUITE_P(Configs, VaeGoldenTest, ::testing::Values("A", "B"));

TEST(VaeTest, EncodeRejectsImageNotMultipleOfDownsampling) {
  absl::StatusOr<AutoencoderKL> vae =
      LoadVae(fd::testing::GoldenPath("A/vae"), torch::kCPU, torch::kFloat32);
  ASSERT_TRUE(vae.ok()) << vae.status();
  const int64_t f = (*vae)->downsampling_factor();
  absl::StatusOr<LatentPosterior> posterior = (*vae)->Encode(torch::zeros({1, 3, f + 1, f}));
  EXPECT_EQ(posterior.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StrContains(posterior.status().message(), "multiples"));
  absl::StatusOr<torch::Tensor> decoded = (*vae)->Decode(torch::zeros({1, 3, 4, 4}));
  EXPECT_EQ(decoded.status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace fd::model

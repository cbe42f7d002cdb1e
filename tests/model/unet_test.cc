// UNet2DConditionModel (8-channel conv_in) against the diffusers goldens
// (configs A and B): noise prediction with and without the ControlNet
// residuals and every debug activation (time embedding, each down block's
// hidden states and skip tensors, mid block, up blocks, output norm).
// Config B's 12x16 latent exercises the explicit upsample_size path.
#include "model/networks/unet.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <string>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "tests/model/network_golden.h"
#include "tests/testing/golden.h"
#include "tests/testing/tensor_matchers.h"

namespace fd::model {
namespace {

using testing::GoldenClose;
using testing::GoldenTensor;
using testing::ReadGolden;

// The ControlNet residuals of controlnet.safetensors, in UNet order (down
// residuals, then the mid residual).
std::vector<torch::Tensor> GoldenResiduals(const std::string& config) {
  const auto controlnet = ReadGolden(config + "/golden/controlnet.safetensors");
  std::vector<torch::Tensor> residuals;
  for (int i = 0; controlnet.count(absl::StrCat("down_block_res_samples.", i)); ++i) {
    residuals.push_back(controlnet.at(absl::StrCat("down_block_res_samples.", i)));
  }
  residuals.push_back(GoldenTensor(controlnet, "mid_block_res_sample"));
  return residuals;
}

class UNetGoldenTest : public ::testing::TestWithParam<std::string> {};

TEST_P(UNetGoldenTest, MatchesDiffusers) {
  const std::string config = GetParam();
  absl::StatusOr<UNet2DConditionModel> unet =
      LoadUNet(fd::testing::GoldenPath(config + "/unet"), torch::kCPU, torch::kFloat32);
  ASSERT_TRUE(unet.ok()) << unet.status();
  const auto in = ReadGolden(config + "/golden/inputs.safetensors");
  const auto vae = ReadGolden(config + "/golden/vae.safetensors");
  const auto golden = ReadGolden(config + "/golden/unet.safetensors");
  const std::string tag = config + "/unet: ";

  // The UNet input is cat([noisy latent, previous-frame latent], 1).
  torch::Tensor sample =
      torch::cat({GoldenTensor(in, "noisy_latent"), GoldenTensor(vae, "prev_latent")}, 1);
  ASSERT_TRUE(torch::equal(sample, GoldenTensor(golden, "sample")));
  const std::vector<torch::Tensor> residuals = GoldenResiduals(config);
  ASSERT_EQ(static_cast<int64_t>(residuals.size()), (*unet)->num_down_residuals() + 1);

  DebugTaps taps;
  absl::StatusOr<torch::Tensor> with_controlnet =
      (*unet)->Run(sample, GoldenTensor(in, "timestep"), GoldenTensor(in, "encoder_hidden_states"),
                   residuals, &taps);
  ASSERT_TRUE(with_controlnet.ok()) << with_controlnet.status();
  EXPECT_TRUE(GoldenClose(tag + "noise_pred_with_controlnet", *with_controlnet,
                          GoldenTensor(golden, "noise_pred_with_controlnet")));
  int debug_tensors = 0;
  for (const auto& [key, expected] : golden) {
    if (!absl::StartsWith(key, "debug.")) continue;
    ++debug_tensors;
    const std::string name = key.substr(6);
    ASSERT_TRUE(taps.count(name)) << "no activation recorded for " << key;
    EXPECT_TRUE(GoldenClose(tag + key, taps[name], expected));
  }
  EXPECT_GT(debug_tensors, 0);

  absl::StatusOr<torch::Tensor> without_controlnet =
      (*unet)->Run(sample, GoldenTensor(in, "timestep"), GoldenTensor(in, "encoder_hidden_states"));
  ASSERT_TRUE(without_controlnet.ok()) << without_controlnet.status();
  EXPECT_TRUE(GoldenClose(tag + "noise_pred_without_controlnet", *without_controlnet,
                          GoldenTensor(golden, "noise_pred_without_controlnet")));
}

INSTANTIATE_TEST_SUITE_P(Configs, UNetGoldenTest, ::testing::Values("A", "B"));

TEST(UNetTest, ScalarAndPerItemTimestepsGiveTheSameResult) {
  absl::StatusOr<UNet2DConditionModel> unet =
      LoadUNet(fd::testing::GoldenPath("B/unet"), torch::kCPU, torch::kFloat32);
  ASSERT_TRUE(unet.ok()) << unet.status();
  const auto in = ReadGolden("B/golden/inputs.safetensors");
  const auto golden = ReadGolden("B/golden/unet.safetensors");
  torch::Tensor sample = GoldenTensor(golden, "sample");
  torch::Tensor ehs = GoldenTensor(in, "encoder_hidden_states");
  const int64_t t = GoldenTensor(in, "timestep").item<int64_t>();
  absl::StatusOr<torch::Tensor> scalar = (*unet)->Run(sample, torch::tensor(t), ehs);
  absl::StatusOr<torch::Tensor> per_item =
      (*unet)->Run(sample, torch::full({sample.size(0)}, t, torch::kInt64), ehs);
  ASSERT_TRUE(scalar.ok()) << scalar.status();
  ASSERT_TRUE(per_item.ok()) << per_item.status();
  EXPECT_TRUE(torch::equal(*scalar, *per_item));
  EXPECT_TRUE(GoldenClose("B/unet: scalar timestep", *scalar,
                          GoldenTensor(golden, "noise_pred_without_controlnet")));
  // Different timesteps per item: each item equals its own single-item run.
  if (sample.size(0) >= 2) {
    torch::Tensor ts = torch::tensor({t, t + 100}, torch::kInt64);
    absl::StatusOr<torch::Tensor> mixed =
        (*unet)->Run(sample.slice(0, 0, 2), ts, ehs.slice(0, 0, 2));
    absl::StatusOr<torch::Tensor> second =
        (*unet)->Run(sample.slice(0, 1, 2), torch::tensor({t + 100}), ehs.slice(0, 1, 2));
    ASSERT_TRUE(mixed.ok()) << mixed.status();
    ASSERT_TRUE(second.ok()) << second.status();
    EXPECT_TRUE(fd::testing::TensorsClose(mixed->slice(0, 1, 2), *second));
    // ... and the timestep really differs from the first item's.
    EXPECT_FALSE(fd::testing::TensorsClose(mixed->slice(0, 1, 2), scalar->slice(0, 1, 2)));
  }
}

TEST(UNetTest, RunValidatesInputs) {
  absl::StatusOr<UNet2DConditionModel> unet =
      LoadUNet(fd::testing::GoldenPath("A/unet"), torch::kCPU, torch::kFloat32);
  ASSERT_TRUE(unet.ok()) << unet.status();
  const auto in = ReadGolden("A/golden/inputs.safetensors");
  torch::Tensor ehs = GoldenTensor(in, "encoder_hidden_states");
  torch::Tensor latent = GoldenTensor(in, "noisy_latent");
  // 4 channels only (the previous-frame latent is missing).
  absl::StatusOr<torch::Tensor> out = (*unet)->Run(latent, torch::tensor(1), ehs);
  EXPECT_EQ(out.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StrContains(out.status().message(), "sample"));
  torch::Tensor sample = torch::cat({latent, latent}, 1);
  out = (*unet)->Run(sample, torch::tensor(1), ehs.slice(2, 0, 3));
  EXPECT_EQ(out.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StrContains(out.status().message(), "encoder_hidden_states"));
  out = (*unet)->Run(sample, torch::tensor(1), ehs, {latent});
  EXPECT_EQ(out.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StrContains(out.status().message(), "residual"));
  // The right number of residuals, but the mid one has the wrong shape.
  std::vector<torch::Tensor> residuals = GoldenResiduals("A");
  residuals.back() = residuals.back().slice(1, 0, 1);
  out = (*unet)->Run(sample, torch::tensor(1), ehs, residuals);
  EXPECT_EQ(out.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StrContains(out.status().message(), "(mid)")) << out.status();
}

}  // namespace
}  // namespace fd::model

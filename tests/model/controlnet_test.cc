// ControlNetModel / ControlNetModelEx against the diffusers goldens (config A
// and B with diffusers' condition encoder, config A's controlnet_fd with the
// FrameDiffuser 9-conv encoder): residuals at conditioning scale 1 and 0.5
// and every debug activation.
#include "model/networks/controlnet.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <string>
#include <tuple>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "tests/model/network_golden.h"
#include "tests/testing/golden.h"

namespace fd::model {
namespace {

using testing::GoldenClose;
using testing::GoldenTensor;
using testing::ReadGolden;

// (config, model folder = golden file stem)
using ControlNetCase = std::tuple<std::string, std::string>;

class ControlNetGoldenTest : public ::testing::TestWithParam<ControlNetCase> {};

TEST_P(ControlNetGoldenTest, MatchesDiffusers) {
  const auto& [config, name] = GetParam();
  absl::StatusOr<ControlNetModel> controlnet =
      LoadControlNet(fd::testing::GoldenPath(config + "/" + name), torch::kCPU, torch::kFloat32);
  ASSERT_TRUE(controlnet.ok()) << controlnet.status();
  EXPECT_EQ((*controlnet)->embedding_kind(), name == "controlnet_fd"
                                                 ? ControlNetEmbeddingKind::kFrameDiffuserEx
                                                 : ControlNetEmbeddingKind::kDiffusers);
  const auto in = ReadGolden(config + "/golden/inputs.safetensors");
  const auto golden = ReadGolden(config + "/golden/" + name + ".safetensors");
  const std::string tag = config + "/" + name + ": ";

  DebugTaps taps;
  absl::StatusOr<std::vector<torch::Tensor>> residuals =
      (*controlnet)
          ->Run(GoldenTensor(in, "noisy_latent"), GoldenTensor(in, "timestep"),
                GoldenTensor(in, "encoder_hidden_states"), GoldenTensor(in, "controlnet_cond"), 1.0,
                &taps);
  ASSERT_TRUE(residuals.ok()) << residuals.status();
  int num_down = 0;
  while (golden.count(absl::StrCat("down_block_res_samples.", num_down))) ++num_down;
  ASSERT_GT(num_down, 0);
  ASSERT_EQ(residuals->size(), static_cast<size_t>(num_down + 1));
  for (int i = 0; i < num_down; ++i) {
    const std::string key = absl::StrCat("down_block_res_samples.", i);
    EXPECT_TRUE(GoldenClose(tag + key, (*residuals)[i], GoldenTensor(golden, key)));
  }
  EXPECT_TRUE(GoldenClose(tag + "mid_block_res_sample", residuals->back(),
                          GoldenTensor(golden, "mid_block_res_sample")));

  int debug_tensors = 0;
  for (const auto& [key, expected] : golden) {
    if (!absl::StartsWith(key, "debug.")) continue;
    ++debug_tensors;
    const std::string tap = key.substr(6);
    ASSERT_TRUE(taps.count(tap)) << "no activation recorded for " << key;
    EXPECT_TRUE(GoldenClose(tag + key, taps[tap], expected));
  }
  EXPECT_GT(debug_tensors, 0);

  absl::StatusOr<std::vector<torch::Tensor>> half =
      (*controlnet)
          ->Run(GoldenTensor(in, "noisy_latent"), GoldenTensor(in, "timestep"),
                GoldenTensor(in, "encoder_hidden_states"), GoldenTensor(in, "controlnet_cond"),
                0.5);
  ASSERT_TRUE(half.ok()) << half.status();
  EXPECT_TRUE(GoldenClose(tag + "down_block_res_samples.0.scale0.5", half->front(),
                          GoldenTensor(golden, "down_block_res_samples.0.scale0.5")));
  EXPECT_TRUE(GoldenClose(tag + "mid_block_res_sample.scale0.5", half->back(),
                          GoldenTensor(golden, "mid_block_res_sample.scale0.5")));
}

INSTANTIATE_TEST_SUITE_P(Configs, ControlNetGoldenTest,
                         ::testing::Values(ControlNetCase{"A", "controlnet"},
                                           ControlNetCase{"B", "controlnet"},
                                           ControlNetCase{"A", "controlnet_fd"}),
                         [](const auto& info) {
                           return std::get<0>(info.param) + "_" + std::get<1>(info.param);
                         });

TEST(ControlNetTest, RunRejectsConditionOfWrongSize) {
  absl::StatusOr<ControlNetModel> controlnet =
      LoadControlNet(fd::testing::GoldenPath("A/controlnet"), torch::kCPU, torch::kFloat32);
  ASSERT_TRUE(controlnet.ok()) << controlnet.status();
  const auto in = ReadGolden("A/golden/inputs.safetensors");
  torch::Tensor cond = GoldenTensor(in, "controlnet_cond");
  absl::StatusOr<std::vector<torch::Tensor>> residuals =
      (*controlnet)
          ->Run(GoldenTensor(in, "noisy_latent"), GoldenTensor(in, "timestep"),
                GoldenTensor(in, "encoder_hidden_states"), cond.slice(1, 0, 3));
  EXPECT_EQ(residuals.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StrContains(residuals.status().message(), "controlnet_cond"));
}

}  // namespace
}  // namespace fd::model

// UNet + LoRA (diffusers pytorch_lora_weights.safetensors) against the
// unet_lora goldens of configs A and B: merged at scale 1.0 and 0.5 (with the
// merged weights themselves), live (unmerged) at 1.0, and a live adapter whose
// scale is changed to 0.5 afterwards.
#include <gtest/gtest.h>
#include <torch/torch.h>

#include <map>
#include <string>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "model/checkpoint/safetensors.h"
#include "model/lora/apply_lora.h"
#include "model/lora/lora_file.h"
#include "model/networks/unet.h"
#include "tests/model/network_golden.h"
#include "tests/testing/golden.h"

namespace fd::model {
namespace {

using testing::GoldenClose;
using testing::GoldenTensor;
using testing::ReadGolden;

class UNetLoraGoldenTest : public ::testing::TestWithParam<std::string> {
 protected:
  void SetUp() override {
    config_ = GetParam();
    in_ = ReadGolden(config_ + "/golden/inputs.safetensors");
    golden_ = ReadGolden(config_ + "/golden/unet_lora.safetensors");
    sample_ = GoldenTensor(ReadGolden(config_ + "/golden/unet.safetensors"), "sample");
    const auto controlnet = ReadGolden(config_ + "/golden/controlnet.safetensors");
    for (int i = 0; controlnet.count(absl::StrCat("down_block_res_samples.", i)); ++i) {
      residuals_.push_back(controlnet.at(absl::StrCat("down_block_res_samples.", i)));
    }
    residuals_.push_back(GoldenTensor(controlnet, "mid_block_res_sample"));
    absl::StatusOr<LoraWeights> lora = LoadLoraWeights(
        fd::testing::GoldenPath(config_ + "/unet_lora/pytorch_lora_weights.safetensors"));
    ASSERT_TRUE(lora.ok()) << lora.status();
    lora_ = *std::move(lora);
  }

  UNet2DConditionModel LoadBaseUNet() {
    absl::StatusOr<UNet2DConditionModel> unet =
        LoadUNet(fd::testing::GoldenPath(config_ + "/unet"), torch::kCPU, torch::kFloat32);
    EXPECT_TRUE(unet.ok()) << unet.status();
    return unet.ok() ? *unet : UNet2DConditionModel(nullptr);
  }

  torch::Tensor Predict(UNet2DConditionModel& unet, bool with_controlnet) {
    absl::StatusOr<torch::Tensor> out = unet->Run(
        sample_, GoldenTensor(in_, "timestep"), GoldenTensor(in_, "encoder_hidden_states"),
        with_controlnet ? residuals_ : std::vector<torch::Tensor>{});
    EXPECT_TRUE(out.ok()) << out.status();
    return out.ok() ? *out : torch::Tensor();
  }

  std::string Tag(const std::string& name) const { return config_ + "/unet_lora: " + name; }

  std::string config_;
  std::map<std::string, torch::Tensor> in_, golden_;
  torch::Tensor sample_;
  std::vector<torch::Tensor> residuals_;
  LoraWeights lora_;
};

TEST_P(UNetLoraGoldenTest, MergedAtScaleOne) {
  UNet2DConditionModel unet = LoadBaseUNet();
  ASSERT_TRUE(unet);
  ASSERT_TRUE(ApplyLora(*unet, lora_, LoraMode::kMerged, 1.0).ok());
  const std::string prefix = "merged_weight.scale1.0.";
  int weights_checked = 0;
  for (const auto& [key, expected] : golden_) {
    if (!absl::StartsWith(key, prefix)) continue;
    const std::string param = key.substr(prefix.size());
    torch::Tensor* actual = unet->named_parameters().find(param);
    ASSERT_NE(actual, nullptr) << "no parameter " << param;
    EXPECT_TRUE(GoldenClose(Tag(key), *actual, expected));
    ++weights_checked;
  }
  EXPECT_GT(weights_checked, 0);
  EXPECT_TRUE(GoldenClose(Tag("noise_pred_merged.scale1.0"), Predict(unet, true),
                          GoldenTensor(golden_, "noise_pred_merged.scale1.0")));
  EXPECT_TRUE(GoldenClose(Tag("noise_pred_merged_without_controlnet.scale1.0"),
                          Predict(unet, false),
                          GoldenTensor(golden_, "noise_pred_merged_without_controlnet.scale1.0")));
}

TEST_P(UNetLoraGoldenTest, MergedAtScaleHalf) {
  UNet2DConditionModel unet = LoadBaseUNet();
  ASSERT_TRUE(unet);
  ASSERT_TRUE(ApplyLora(*unet, lora_, LoraMode::kMerged, 0.5).ok());
  EXPECT_TRUE(GoldenClose(Tag("noise_pred_merged.scale0.5 (merged)"), Predict(unet, true),
                          GoldenTensor(golden_, "noise_pred_merged.scale0.5")));
}

TEST_P(UNetLoraGoldenTest, LiveAtScaleOneThenHalf) {
  UNet2DConditionModel unet = LoadBaseUNet();
  ASSERT_TRUE(unet);
  std::vector<std::string> keys_before = unet->named_parameters().keys();
  std::map<std::string, torch::Tensor> weights_before;
  for (const auto& item : unet->named_parameters())
    weights_before[item.key()] = item.value().clone();
  ASSERT_TRUE(ApplyLora(*unet, lora_, LoraMode::kLive, 1.0).ok());
  // Live adapters are neither parameters nor merged into the weights.
  EXPECT_EQ(unet->named_parameters().keys(), keys_before);
  EXPECT_TRUE(unet->named_buffers().is_empty());
  for (const auto& item : unet->named_parameters()) {
    ASSERT_TRUE(torch::equal(item.value(), weights_before.at(item.key()))) << item.key();
  }
  EXPECT_TRUE(GoldenClose(Tag("noise_pred_runtime.scale1.0"), Predict(unet, true),
                          GoldenTensor(golden_, "noise_pred_runtime.scale1.0")));
  // PEFT set_scale: same adapters, scale 0.5 = the merged-at-0.5 result.
  SetLoraScale(*unet, 0.5);
  EXPECT_TRUE(GoldenClose(Tag("noise_pred_merged.scale0.5 (live)"), Predict(unet, true),
                          GoldenTensor(golden_, "noise_pred_merged.scale0.5")));
  // Removing the adapters gives the base UNet back.
  RemoveLiveLora(*unet);
  const auto base = ReadGolden(config_ + "/golden/unet.safetensors");
  EXPECT_TRUE(GoldenClose(Tag("without LoRA"), Predict(unet, true),
                          GoldenTensor(base, "noise_pred_with_controlnet")));
}

TEST_P(UNetLoraGoldenTest, LiveAtScaleHalf) {
  UNet2DConditionModel unet = LoadBaseUNet();
  ASSERT_TRUE(unet);
  ASSERT_TRUE(ApplyLora(*unet, lora_, LoraMode::kLive, 0.5).ok());
  EXPECT_TRUE(GoldenClose(Tag("noise_pred_merged.scale0.5 (live 0.5)"), Predict(unet, true),
                          GoldenTensor(golden_, "noise_pred_merged.scale0.5")));
}

INSTANTIATE_TEST_SUITE_P(Configs, UNetLoraGoldenTest, ::testing::Values("A", "B"));

}  // namespace
}  // namespace fd::model

// The FrameDiffuser authors' checkpoint layout (fd_pipeline/model):
// UNet2DConditionModelEx (config in_channels 4, conv_in weight 8 channels),
// ControlNetModelEx (9-conv G-buffer encoder), AutoencoderKL and the PEFT
// ControlLoRA, against the goldens of the authors' own pipeline run
// (fd_pipeline/golden/e2e.safetensors, lora_merge.safetensors): the
// ControlNet residuals of step 0 and the VAE posterior of every frame, and
// the step-0 UNet prediction without LoRA, with the live (unmerged) LoRA the
// pipeline runs, and with the merged LoRA.
#include <gtest/gtest.h>
#include <torch/torch.h>

#include <map>
#include <memory>
#include <string>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "model/lora/apply_lora.h"
#include "model/lora/lora_file.h"
#include "model/networks/controlnet.h"
#include "model/networks/unet.h"
#include "model/networks/vae.h"
#include "tests/model/network_golden.h"
#include "tests/testing/golden.h"

namespace fd::model {
namespace {

using testing::GoldenClose;
using testing::GoldenTensor;
using testing::ReadGolden;

std::string ModelDir(const std::string& name) {
  return fd::testing::GoldenPath("fd_pipeline/model/" + name);
}

class FrameDiffuserCheckpointTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    e2e_ =
        new std::map<std::string, torch::Tensor>(ReadGolden("fd_pipeline/golden/e2e.safetensors"));
    merge_ = new std::map<std::string, torch::Tensor>(
        ReadGolden("fd_pipeline/golden/lora_merge.safetensors"));
    prompt_embeds_ = new torch::Tensor(
        GoldenTensor(ReadGolden("fd_pipeline/model/prompt_embeds.safetensors"), "prompt_embeds"));
  }
  static void TearDownTestSuite() {
    delete e2e_;
    delete merge_;
    delete prompt_embeds_;
  }

  // The frames of the autoregressive run: frame{f}.timesteps present.
  static std::vector<std::string> Frames() {
    std::vector<std::string> frames;
    for (int f = 0; e2e_->count(absl::StrCat("frame", f, ".timesteps")); ++f) {
      frames.push_back(absl::StrCat("frame", f));
    }
    EXPECT_FALSE(frames.empty());
    return frames;
  }

  static torch::Tensor E2e(const std::string& key) { return GoldenTensor(*e2e_, key); }
  // timesteps[0] of a frame as a 0-d int64 tensor (what the pipeline passes).
  static torch::Tensor FirstTimestep(const std::string& frame) {
    return E2e(frame + ".timesteps")[0];
  }
  // The step-0 ControlNet residuals the reference computed, in UNet order.
  static std::vector<torch::Tensor> GoldenResiduals(const std::string& frame) {
    std::vector<torch::Tensor> residuals;
    const std::string prefix = frame + ".debug.step0.controlnet_down.";
    for (int j = 0; e2e_->count(absl::StrCat(prefix, j)); ++j) {
      residuals.push_back(e2e_->at(absl::StrCat(prefix, j)));
    }
    residuals.push_back(E2e(frame + ".debug.step0.controlnet_mid"));
    return residuals;
  }
  // UNet input of step 0: cat([x_T, prev_latent], 1).
  static torch::Tensor Step0Sample(const std::string& frame) {
    return torch::cat({E2e(frame + ".init_noise"), E2e(frame + ".prev_latent")}, 1);
  }

  static UNet2DConditionModel LoadFdUNet() {
    absl::StatusOr<UNet2DConditionModel> unet =
        LoadUNet(ModelDir("unet"), torch::kCPU, torch::kFloat32);
    EXPECT_TRUE(unet.ok()) << unet.status();
    return unet.ok() ? *unet : UNet2DConditionModel(nullptr);
  }

  static LoraWeights LoadControlLora() {
    absl::StatusOr<LoraWeights> lora =
        LoadLoraWeights(ModelDir("controllora/pytorch_lora_weights.safetensors"));
    EXPECT_TRUE(lora.ok()) << lora.status();
    return lora.ok() ? *std::move(lora) : LoraWeights();
  }

  static std::map<std::string, torch::Tensor>* e2e_;
  static std::map<std::string, torch::Tensor>* merge_;
  static torch::Tensor* prompt_embeds_;
};

std::map<std::string, torch::Tensor>* FrameDiffuserCheckpointTest::e2e_ = nullptr;
std::map<std::string, torch::Tensor>* FrameDiffuserCheckpointTest::merge_ = nullptr;
torch::Tensor* FrameDiffuserCheckpointTest::prompt_embeds_ = nullptr;

TEST_F(FrameDiffuserCheckpointTest, ControlNetExResidualsOfStepZero) {
  absl::StatusOr<ControlNetModel> controlnet =
      LoadControlNet(ModelDir("controlnet"), torch::kCPU, torch::kFloat32);
  ASSERT_TRUE(controlnet.ok()) << controlnet.status();
  EXPECT_EQ((*controlnet)->embedding_kind(), ControlNetEmbeddingKind::kFrameDiffuserEx);
  for (const std::string& frame : Frames()) {
    absl::StatusOr<std::vector<torch::Tensor>> residuals =
        (*controlnet)
            ->Run(E2e(frame + ".init_noise"), FirstTimestep(frame), *prompt_embeds_,
                  E2e(frame + ".controlnet_cond"), 1.0);
    ASSERT_TRUE(residuals.ok()) << residuals.status();
    const std::vector<torch::Tensor> expected = GoldenResiduals(frame);
    ASSERT_EQ(residuals->size(), expected.size());
    for (size_t j = 0; j < expected.size(); ++j) {
      const std::string name = j + 1 == expected.size()
                                   ? frame + ".debug.step0.controlnet_mid"
                                   : absl::StrCat(frame, ".debug.step0.controlnet_down.", j);
      EXPECT_TRUE(GoldenClose("fd_pipeline/e2e controlnet: " + name, (*residuals)[j], expected[j]));
    }
  }
}

TEST_F(FrameDiffuserCheckpointTest, VaePosteriorAndPreviousFrameLatent) {
  absl::StatusOr<AutoencoderKL> vae = LoadVae(ModelDir("vae"), torch::kCPU, torch::kFloat32);
  ASSERT_TRUE(vae.ok()) << vae.status();
  for (const std::string& frame : Frames()) {
    absl::StatusOr<LatentPosterior> posterior = (*vae)->Encode(E2e(frame + ".vae_encode_input"));
    ASSERT_TRUE(posterior.ok()) << posterior.status();
    const std::string tag = "fd_pipeline/e2e vae: " + frame;
    EXPECT_TRUE(
        GoldenClose(tag + ".posterior_mean", posterior->mean, E2e(frame + ".posterior_mean")));
    EXPECT_TRUE(GoldenClose(tag + ".posterior_std", posterior->std, E2e(frame + ".posterior_std")));
    torch::Tensor prev_latent =
        posterior->Sample(E2e(frame + ".vae_sample_noise")) * (*vae)->config().scaling_factor;
    EXPECT_TRUE(GoldenClose(tag + ".prev_latent", prev_latent, E2e(frame + ".prev_latent")));
  }
}

TEST_F(FrameDiffuserCheckpointTest, UNetExLoadsTheEightChannelConvIn) {
  UNet2DConditionModel unet = LoadFdUNet();
  ASSERT_TRUE(unet);
  EXPECT_EQ(unet->config().in_channels, 4);
  EXPECT_EQ(unet->input_channels(), 8);
  EXPECT_EQ(unet->conv_in->weight.size(1), 8);
  // The base UNet (no LoRA) on frame 0's step-0 inputs.
  absl::StatusOr<torch::Tensor> out = unet->Run(Step0Sample("frame0"), FirstTimestep("frame0"),
                                                *prompt_embeds_, GoldenResiduals("frame0"));
  ASSERT_TRUE(out.ok()) << out.status();
  EXPECT_TRUE(GoldenClose("fd_pipeline/lora_merge: frame0.step0.noise_pred_no_lora", *out,
                          GoldenTensor(*merge_, "frame0.step0.noise_pred_no_lora")));
}

TEST_F(FrameDiffuserCheckpointTest, UNetWithLiveControlLoraAsThePipelineRunsIt) {
  UNet2DConditionModel unet = LoadFdUNet();
  ASSERT_TRUE(unet);
  const LoraWeights lora = LoadControlLora();
  ASSERT_TRUE(ApplyLora(*unet, lora, LoraMode::kLive, 1.0).ok());
  for (const std::string& frame : Frames()) {
    absl::StatusOr<torch::Tensor> out = unet->Run(Step0Sample(frame), FirstTimestep(frame),
                                                  *prompt_embeds_, GoldenResiduals(frame));
    ASSERT_TRUE(out.ok()) << out.status();
    EXPECT_TRUE(GoldenClose("fd_pipeline/e2e unet: " + frame + ".step.0.noise_pred", *out,
                            E2e(frame + ".step.0.noise_pred")));
  }
}

TEST_F(FrameDiffuserCheckpointTest, UNetWithMergedControlLora) {
  UNet2DConditionModel unet = LoadFdUNet();
  ASSERT_TRUE(unet);
  const LoraWeights lora = LoadControlLora();
  EXPECT_EQ(static_cast<int64_t>(lora.modules.size()),
            GoldenTensor(*merge_, "n_merged_modules").item<int64_t>());
  ASSERT_TRUE(ApplyLora(*unet, lora, LoraMode::kMerged, 1.0).ok());
  int checked = 0;
  for (const auto& [key, expected] : *merge_) {
    if (!absl::StartsWith(key, "merged_weight.")) continue;
    torch::Tensor* actual = unet->named_parameters().find(key.substr(14));
    ASSERT_NE(actual, nullptr) << key;
    EXPECT_TRUE(GoldenClose("fd_pipeline/lora_merge: " + key, *actual, expected));
    ++checked;
  }
  EXPECT_GT(checked, 0);
  for (const std::string& frame : Frames()) {
    const std::string key = frame + ".step0.noise_pred_merged";
    if (!merge_->count(key)) continue;
    absl::StatusOr<torch::Tensor> out = unet->Run(Step0Sample(frame), FirstTimestep(frame),
                                                  *prompt_embeds_, GoldenResiduals(frame));
    ASSERT_TRUE(out.ok()) << out.status();
    EXPECT_TRUE(GoldenClose("fd_pipeline/lora_merge: " + key, *out, merge_->at(key)));
  }
}

}  // namespace
}  // namespace fd::model

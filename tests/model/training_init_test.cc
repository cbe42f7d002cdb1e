// model/presets/training_init.h: fresh weights, the authors' stage transitions and
// trainable LoRA. The zero initialisations are exact: a fresh stage-1
// ControlNet adds nothing to the base UNet's prediction, and a fresh stage-2
// ControlLoRA + widened conv_in leave the stage-1 prediction bitwise as it was.
#include "model/presets/training_init.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <string>
#include <vector>

#include "model/checkpoint/checkpoint_writer.h"
#include "model/networks/model_configs.h"
#include "model/pipeline/conditioning.h"
#include "model/presets/presets.h"
#include "nlohmann/json.hpp"

namespace fd::model {
namespace {

struct TinyNetworks {
  UNet2DConditionModel unet{nullptr};  // base: 4-channel conv_in
  ControlNetConfig controlnet_config;
  std::string unet_json;
};

TinyNetworks MakeTinyBase(uint64_t seed) {
  TinyNetworks nets;
  absl::StatusOr<PresetConfigs> configs = GetPresetConfigs("tiny");
  EXPECT_TRUE(configs.ok()) << configs.status();
  nets.unet_json = configs->unet;
  absl::StatusOr<UNet2DConditionConfig> config =
      ParseUNet2DConditionConfig(configs->unet, "tiny unet");
  EXPECT_TRUE(config.ok()) << config.status();
  absl::StatusOr<UNet2DConditionModel> unet = MakeUNet(*config);
  EXPECT_TRUE(unet.ok()) << unet.status();
  nets.unet = *unet;
  EXPECT_TRUE(InitializeDefaultWeights(*nets.unet, seed).ok());
  absl::StatusOr<std::string> cn_json =
      ControlNetConfigJsonFromUNet(configs->unet, {8, 16, 16, 32});
  EXPECT_TRUE(cn_json.ok()) << cn_json.status();
  absl::StatusOr<ControlNetConfig> cn_config = ParseControlNetConfig(*cn_json, "derived");
  EXPECT_TRUE(cn_config.ok()) << cn_config.status();
  nets.controlnet_config = *cn_config;
  return nets;
}

struct Inputs {
  torch::Tensor noisy, prev, t, embeds, cond;
};

Inputs MakeInputs() {
  torch::manual_seed(3);
  return {torch::randn({2, 4, 8, 8}), torch::randn({2, 4, 8, 8}), torch::tensor({10, 900}),
          torch::randn({2, 7, 32}), torch::rand({2, 10, 64, 64}) * 2 - 1};
}

bool BitwiseEqual(const torch::Tensor& a, const torch::Tensor& b) {
  return a.sizes() == b.sizes() && torch::equal(a, b);
}

TEST(InitializeDefaultWeightsTest, FollowsTorchDefaultsAndIsDeterministic) {
  TinyNetworks a = MakeTinyBase(5);
  TinyNetworks b = MakeTinyBase(5);
  TinyNetworks c = MakeTinyBase(6);
  auto pa = a.unet->named_parameters();
  auto pb = b.unet->named_parameters();
  auto pc = c.unet->named_parameters();
  bool any_differs = false;
  for (const auto& item : pa) {
    EXPECT_TRUE(torch::equal(item.value(), pb[item.key()])) << item.key();
    any_differs = any_differs || !torch::equal(item.value(), pc[item.key()]);
  }
  EXPECT_TRUE(any_differs);
  // conv_in: fan_in = 4 * 3 * 3, so |w| <= 1/6.
  const torch::Tensor& w = pa["conv_in.weight"];
  EXPECT_LE(w.abs().max().item<double>(), 1.0 / 6.0);
  EXPECT_GT(w.abs().max().item<double>(), 0.1);
  EXPECT_TRUE(
      torch::equal(pa["conv_norm_out.weight"], torch::ones_like(pa["conv_norm_out.weight"])));
  EXPECT_TRUE(torch::equal(pa["conv_norm_out.bias"], torch::zeros_like(pa["conv_norm_out.bias"])));
}

TEST(ControlNetFromUNetTest, CopiesTheEncoderAndAddsExactlyZero) {
  TinyNetworks nets = MakeTinyBase(1);
  absl::StatusOr<ControlNetModel> controlnet =
      ControlNetFromUNet(*nets.unet, nets.controlnet_config, 2);
  ASSERT_TRUE(controlnet.ok()) << controlnet.status();
  auto cn = (*controlnet)->named_parameters();
  auto un = nets.unet->named_parameters();
  EXPECT_TRUE(torch::equal(cn["conv_in.weight"], un["conv_in.weight"]));
  EXPECT_TRUE(torch::equal(cn["down_blocks.0.resnets.0.conv1.weight"],
                           un["down_blocks.0.resnets.0.conv1.weight"]));
  EXPECT_TRUE(torch::equal(cn["mid_block.attentions.0.proj_in.weight"],
                           un["mid_block.attentions.0.proj_in.weight"]));
  EXPECT_EQ(cn["controlnet_mid_block.weight"].abs().sum().item<double>(), 0.0);
  EXPECT_EQ(cn["controlnet_cond_embedding.16.weight"].abs().sum().item<double>(), 0.0);
  EXPECT_GT(cn["controlnet_cond_embedding.0.weight"].abs().sum().item<double>(), 0.0);

  torch::NoGradGuard no_grad;
  Inputs in = MakeInputs();
  const torch::Tensor base = nets.unet->forward(in.noisy, in.t, in.embeds);
  std::vector<torch::Tensor> residuals = (*controlnet)->forward(in.noisy, in.t, in.embeds, in.cond);
  for (const torch::Tensor& r : residuals) EXPECT_EQ(r.abs().max().item<double>(), 0.0);
  EXPECT_TRUE(BitwiseEqual(nets.unet->forward(in.noisy, in.t, in.embeds, residuals), base));
}

TEST(WidenConvInTest, FreshLoraAndWideConvInKeepTheStageOnePrediction) {
  TinyNetworks nets = MakeTinyBase(1);
  absl::StatusOr<ControlNetModel> controlnet =
      ControlNetFromUNet(*nets.unet, nets.controlnet_config, 2);
  ASSERT_TRUE(controlnet.ok());
  // A trained-looking stage-1 ControlNet: non-zero residuals.
  {
    torch::NoGradGuard no_grad;
    for (torch::Tensor& p : (*controlnet)->parameters()) p.add_(torch::randn_like(p) * 0.05);
  }
  absl::StatusOr<UNet2DConditionModel> wide = WidenConvIn(*nets.unet);
  ASSERT_TRUE(wide.ok()) << wide.status();
  EXPECT_EQ((*wide)->input_channels(), 8);
  EXPECT_EQ(nets.unet->input_channels(), 4);
  EXPECT_FALSE(WidenConvIn(**wide).ok());

  torch::NoGradGuard no_grad;
  Inputs in = MakeInputs();
  std::vector<torch::Tensor> residuals = (*controlnet)->forward(in.noisy, in.t, in.embeds, in.cond);
  // The stage-1 model as the server runs it: conv_in zero-padded to 8 inputs.
  const torch::Tensor stage1 =
      (*wide)->forward(torch::cat({in.noisy, in.prev}, 1), in.t, in.embeds, residuals);
  // The extra channels are exactly ignored.
  EXPECT_TRUE(BitwiseEqual(
      (*wide)->forward(torch::cat({in.noisy, in.prev * 7}, 1), in.t, in.embeds, residuals),
      stage1));
  // Against the 4-channel base itself (another conv shape: float rounding only).
  EXPECT_TRUE(torch::allclose(nets.unet->forward(in.noisy, in.t, in.embeds, residuals), stage1,
                              1e-5, 1e-6));

  absl::StatusOr<TrainableLora> lora = AddTrainableControlLora(**wide, 4, 9);
  ASSERT_TRUE(lora.ok()) << lora.status();
  ASSERT_FALSE(lora->down.empty());
  ASSERT_EQ(lora->down.size(), lora->up.size());
  for (size_t i = 0; i < lora->down.size(); ++i) {
    EXPECT_TRUE(lora->down[i].requires_grad());
    EXPECT_EQ(lora->up[i].abs().sum().item<double>(), 0.0);
    // PEFT gaussian: std 1/r.
  }
  torch::Tensor all_down = torch::cat({lora->down[0].flatten(), lora->down[1].flatten()});
  EXPECT_NEAR(all_down.std().item<double>(), 0.25, 0.05);
  EXPECT_TRUE(BitwiseEqual(
      (*wide)->forward(torch::cat({in.noisy, in.prev}, 1), in.t, in.embeds, residuals), stage1));
  // full_skip_attn: no adapter on attention projections, one on conv_in.
  absl::StatusOr<std::map<std::string, torch::Tensor>> saved =
      LiveLoraStateDict(**wide, torch::kFloat32);
  ASSERT_TRUE(saved.ok()) << saved.status();
  EXPECT_TRUE(saved->count("unet.conv_in.lora_A.weight"));
  EXPECT_EQ(saved->at("unet.conv_in.lora_A.weight").sizes(), torch::IntArrayRef({4, 8, 3, 3}));
  EXPECT_TRUE(
      saved->count("unet.down_blocks.0.attentions.0.transformer_blocks.0.ff.net.2.lora_B.weight"));
  for (const auto& [key, value] : *saved) {
    EXPECT_EQ(key.find(".to_q."), std::string::npos) << key;
    EXPECT_EQ(key.find(".to_out.0."), std::string::npos) << key;
  }
  EXPECT_EQ(saved->size(), 2 * lora->down.size());
  EXPECT_FALSE(AddTrainableControlLora(**wide, 4, 9).ok());  // already adapted
}

TEST(WidenConvInTest, GradientsReachLoraAndNotFrozenWeights) {
  TinyNetworks nets = MakeTinyBase(1);
  absl::StatusOr<UNet2DConditionModel> wide = WidenConvIn(*nets.unet);
  ASSERT_TRUE(wide.ok());
  SetRequiresGrad(**wide, false);
  absl::StatusOr<TrainableLora> lora = AddTrainableControlLora(**wide, 2, 1);
  ASSERT_TRUE(lora.ok());
  Inputs in = MakeInputs();
  torch::Tensor out = (*wide)->forward(torch::cat({in.noisy, in.prev}, 1), in.t, in.embeds);
  out.pow(2).mean().backward();
  // B starts at zero, so only B gets a gradient on the first step (PEFT too).
  double up_grad = 0;
  for (const torch::Tensor& up : lora->up) up_grad += up.grad().abs().sum().item<double>();
  EXPECT_GT(up_grad, 0.0);
  for (const torch::Tensor& p : (*wide)->parameters()) EXPECT_FALSE(p.grad().defined());
}

// --basecolor_patches: conv_in grows by the 3 * f * f patch channels after
// the previous latent, they start at zero (the widened copy predicts what the
// base does), the copy's config names them, and the ControlNet's derived
// config does not carry the key.
TEST(WidenConvInTest, BasecolorPatchesWidenConvInAndStartAtZero) {
  TinyNetworks nets = MakeTinyBase(1);
  constexpr int64_t kPatches = 3 * 8 * 8;
  absl::StatusOr<UNet2DConditionModel> wide = WidenConvIn(*nets.unet, kPatches);
  ASSERT_TRUE(wide.ok()) << wide.status();
  EXPECT_EQ((*wide)->input_channels(), 8 + kPatches);
  EXPECT_EQ((*wide)->config().basecolor_patch_channels, kPatches);
  EXPECT_EQ((*wide)->config().FrameDiffuserInputChannels(), 8 + kPatches);
  EXPECT_FALSE(WidenConvIn(**wide, kPatches).ok());  // already widened
  EXPECT_FALSE(WidenConvIn(*nets.unet, 10).ok());    // not 3 * f * f

  torch::NoGradGuard no_grad;
  Inputs in = MakeInputs();
  absl::StatusOr<torch::Tensor> patches = BasecolorPatches(in.cond, 8);
  ASSERT_TRUE(patches.ok()) << patches.status();
  const torch::Tensor with_patches =
      (*wide)->forward(torch::cat({in.noisy, in.prev, *patches}, 1), in.t, in.embeds);
  EXPECT_TRUE(
      torch::allclose(nets.unet->forward(in.noisy, in.t, in.embeds), with_patches, 1e-5, 1e-6));
  // Once conv_in's patch weights are non-zero, the basecolor changes the prediction.
  (*wide)->conv_in->weight.slice(1, 8).normal_(0, 0.1);
  const torch::Tensor trained =
      (*wide)->forward(torch::cat({in.noisy, in.prev, *patches}, 1), in.t, in.embeds);
  const torch::Tensor other_colours =
      (*wide)->forward(torch::cat({in.noisy, in.prev, patches->flip(1)}, 1), in.t, in.embeds);
  EXPECT_GT((trained - other_colours).abs().max().item<double>(), 1e-3);

  nlohmann::json unet = nlohmann::json::parse(nets.unet_json);
  unet["basecolor_patch_channels"] = kPatches;
  absl::StatusOr<std::string> cn_json = ControlNetConfigJsonFromUNet(unet.dump(), {8, 16, 16, 32});
  ASSERT_TRUE(cn_json.ok()) << cn_json.status();
  EXPECT_FALSE(nlohmann::json::parse(*cn_json).contains("basecolor_patch_channels"));
}

TEST(ControlNetConfigJsonFromUNetTest, RejectsTextThatIsNoUNetConfig) {
  EXPECT_FALSE(ControlNetConfigJsonFromUNet("{}").ok());
  EXPECT_FALSE(ControlNetConfigJsonFromUNet("not json").ok());
}

}  // namespace
}  // namespace fd::model

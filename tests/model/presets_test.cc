// model/presets/presets.h: the tiny preset writes a complete FrameDiffuser
// checkpoint that every loader accepts strictly, with every parameter random,
// reproducibly per seed; the sd15 preset has the real SD1.5 shapes.
#include "model/presets/presets.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>

#include "absl/strings/match.h"
#include "model/lora/apply_lora.h"
#include "model/lora/lora_file.h"
#include "model/networks/controlnet.h"
#include "model/networks/model_configs.h"
#include "model/networks/unet.h"
#include "model/networks/vae.h"

namespace fd::model {
namespace {

namespace fs = std::filesystem;

std::string ReadBytes(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
}

class PresetsTest : public ::testing::Test {
 protected:
  void SetUp() override {
    // One folder per test: ctest runs the tests of this file in parallel.
    dir_ = fs::path(::testing::TempDir()) /
           (std::string("fd_checkpoint_maker_") +
            ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }

  std::string Make(const std::string& name, uint64_t seed) {
    MakeCheckpointOptions options;
    options.preset = "tiny";
    options.out_dir = (dir_ / name).string();
    options.seed = seed;
    absl::Status status = MakeCheckpoint(options);
    EXPECT_TRUE(status.ok()) << status;
    return options.out_dir;
  }

  // Every parameter random: no tensor is constant (zero-convs included).
  static void ExpectAllParametersRandom(torch::nn::Module& module) {
    for (const auto& item : module.named_parameters()) {
      EXPECT_GT(item.value().numel(), 1) << item.key();
      EXPECT_GT(item.value().std().item<double>(), 0.0) << item.key() << " is constant";
    }
  }

  fs::path dir_;
};

TEST_F(PresetsTest, TinyCheckpointLoadsStrictlyAndRuns) {
  const std::string dir = Make("tiny", 3);
  absl::StatusOr<UNet2DConditionModel> unet = LoadUNet(dir + "/unet", torch::kCPU, torch::kFloat32);
  ASSERT_TRUE(unet.ok()) << unet.status();
  EXPECT_EQ((*unet)->config().in_channels, 4);
  EXPECT_EQ((*unet)->config().class_name, "UNet2DConditionModelEx");
  EXPECT_EQ((*unet)->input_channels(), 8);
  ExpectAllParametersRandom(**unet);
  absl::StatusOr<ControlNetModel> controlnet =
      LoadControlNet(dir + "/controlnet", torch::kCPU, torch::kFloat32);
  ASSERT_TRUE(controlnet.ok()) << controlnet.status();
  EXPECT_EQ((*controlnet)->embedding_kind(), ControlNetEmbeddingKind::kFrameDiffuserEx);
  ExpectAllParametersRandom(**controlnet);
  absl::StatusOr<AutoencoderKL> vae = LoadVae(dir + "/vae", torch::kCPU, torch::kFloat32);
  ASSERT_TRUE(vae.ok()) << vae.status();
  ExpectAllParametersRandom(**vae);
  EXPECT_TRUE(fs::exists(dir + "/scheduler/scheduler_config.json"));

  // ControlLoRA: FrameDiffuser's full_skip_attn targets (every Linear/Conv2d
  // but the attention projections), PEFT keys, alpha = rank.
  absl::StatusOr<LoraWeights> lora =
      LoadLoraWeights(dir + "/controllora/pytorch_lora_weights.safetensors");
  ASSERT_TRUE(lora.ok()) << lora.status();
  int64_t adaptable = 0, attention_projections = 0;
  for (const auto& item : (*unet)->named_modules("", false)) {
    if (dynamic_cast<LoraAdaptable*>(item.value().get()) == nullptr) continue;
    ++adaptable;
    for (const char* p : {".to_q", ".to_k", ".to_v", ".to_out.0"}) {
      if (absl::EndsWith(item.key(), p)) ++attention_projections;
    }
  }
  EXPECT_GT(attention_projections, 0);
  EXPECT_EQ(static_cast<int64_t>(lora->modules.size()), adaptable - attention_projections);
  EXPECT_TRUE(lora->modules.count("conv_in"));
  EXPECT_EQ(lora->modules.at("conv_in").down.size(1), 8);
  ASSERT_TRUE(ApplyLora(**unet, *lora, LoraMode::kLive, 1.0).ok());

  // One denoising step at the checkpoint's own shapes.
  absl::StatusOr<std::map<std::string, torch::Tensor>> embeds =
      LoadSafetensors(dir + "/prompt_embeds.safetensors");
  ASSERT_TRUE(embeds.ok()) << embeds.status();
  torch::Tensor ehs = embeds->at("prompt_embeds");
  torch::Tensor latent = torch::randn({1, 4, 8, 10});
  absl::StatusOr<LatentPosterior> posterior = (*vae)->Encode(torch::rand({1, 3, 64, 80}) * 2 - 1);
  ASSERT_TRUE(posterior.ok()) << posterior.status();
  absl::StatusOr<std::vector<torch::Tensor>> residuals =
      (*controlnet)->Run(latent, torch::tensor(999), ehs, torch::rand({1, 10, 64, 80}) * 2 - 1);
  ASSERT_TRUE(residuals.ok()) << residuals.status();
  absl::StatusOr<torch::Tensor> noise_pred = (*unet)->Run(
      torch::cat({latent, posterior->mean * 0.18215}, 1), torch::tensor(999), ehs, *residuals);
  ASSERT_TRUE(noise_pred.ok()) << noise_pred.status();
  EXPECT_EQ(noise_pred->sizes(), latent.sizes());
  EXPECT_TRUE(torch::isfinite(*noise_pred).all().item<bool>());
}

TEST_F(PresetsTest, SameSeedSameBytesOtherSeedOtherWeights) {
  const fs::path a = Make("a", 11), b = Make("b", 11), c = Make("c", 12);
  for (const char* file :
       {"unet/diffusion_pytorch_model.safetensors",
        "controlnet/diffusion_pytorch_model.safetensors", "vae/diffusion_pytorch_model.safetensors",
        "controllora/pytorch_lora_weights.safetensors"}) {
    EXPECT_EQ(ReadBytes(a / file), ReadBytes(b / file)) << file;
    EXPECT_NE(ReadBytes(a / file), ReadBytes(c / file)) << file;
  }
}

TEST_F(PresetsTest, Sd15PresetHasTheStableDiffusionShapes) {
  absl::StatusOr<PresetConfigs> configs = GetPresetConfigs("sd15");
  ASSERT_TRUE(configs.ok()) << configs.status();
  absl::StatusOr<UNet2DConditionConfig> unet = ParseUNet2DConditionConfig(configs->unet, "sd15");
  ASSERT_TRUE(unet.ok()) << unet.status();
  EXPECT_EQ(unet->block_out_channels, (std::vector<int64_t>{320, 640, 1280, 1280}));
  EXPECT_EQ(unet->cross_attention_dim.at(0), 768);
  absl::StatusOr<UNetLayout> layout = ComputeUNetLayout(*unet);
  ASSERT_TRUE(layout.ok()) << layout.status();
  EXPECT_EQ(layout->down_blocks.at(0).attention_head_dim, 40);  // 320 / 8 heads
  // The SD1.5 VAE (83,653,863 parameters in diffusers) is small enough to build.
  absl::StatusOr<AutoencoderKLConfig> vae_config = ParseAutoencoderKLConfig(configs->vae, "sd15");
  ASSERT_TRUE(vae_config.ok()) << vae_config.status();
  absl::StatusOr<AutoencoderKL> vae = MakeVae(*vae_config);
  ASSERT_TRUE(vae.ok()) << vae.status();
  int64_t count = 0;
  for (const torch::Tensor& p : (*vae)->parameters()) count += p.numel();
  EXPECT_EQ(count, 83653863);
}

TEST_F(PresetsTest, UnknownPresetIsRejected) {
  MakeCheckpointOptions options;
  options.preset = "huge";
  options.out_dir = (dir_ / "huge").string();
  absl::Status status = MakeCheckpoint(options);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StrContains(status.message(), "tiny")) << status;
  EXPECT_FALSE(fs::exists(dir_ / "huge"));
}

}  // namespace
}  // namespace fd::model

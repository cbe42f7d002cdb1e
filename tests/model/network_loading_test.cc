// Loading the networks from diffusers checkpoint folders: strict loading
// errors (missing key, unexpected key, shape mismatch, missing file), the
// UNet2DConditionModelEx conv_in rule (a 4-channel conv_in is zero-padded to
// 8), named_parameters() == state-dict keys, and dtype/device handling.
#include <gtest/gtest.h>
#include <torch/torch.h>
#include <torch/version.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <map>
#include <string>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "model/checkpoint/safetensors.h"
#include "model/networks/controlnet.h"
#include "model/networks/unet.h"
#include "model/networks/vae.h"
#include "tests/model/network_golden.h"
#include "tests/testing/golden.h"
#include "tests/testing/tensor_matchers.h"

namespace fd::model {
namespace {

namespace fs = std::filesystem;
using testing::GoldenClose;
using testing::GoldenTensor;
using testing::ReadGolden;

// A scratch copy of a golden model folder whose weights can be edited.
class CheckpointCopy {
 public:
  CheckpointCopy(const std::string& golden_model, const std::string& name) {
    dir_ = fs::path(::testing::TempDir()) / ("fd_network_loading_" + name);
    fs::remove_all(dir_);
    fs::create_directories(dir_);
    fs::copy_file(fd::testing::GoldenPath(golden_model + "/config.json"), dir_ / "config.json");
    weights_ = ReadGolden(golden_model + "/diffusion_pytorch_model.safetensors");
  }
  ~CheckpointCopy() { fs::remove_all(dir_); }

  std::map<std::string, torch::Tensor>& weights() { return weights_; }
  std::string dir() const { return dir_.string(); }

  void Write() {
    absl::Status status =
        SaveSafetensors((dir_ / "diffusion_pytorch_model.safetensors").string(), weights_);
    ASSERT_TRUE(status.ok()) << status;
  }
  void ReplaceConfig(const std::string& from, const std::string& to) {
    std::ifstream in(dir_ / "config.json");
    std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    const size_t at = text.find(from);
    ASSERT_NE(at, std::string::npos) << from;
    text.replace(at, from.size(), to);
    std::ofstream(dir_ / "config.json") << text;
  }

 private:
  fs::path dir_;
  std::map<std::string, torch::Tensor> weights_;
};

TEST(NetworkLoadingTest, NamedParametersAreTheCheckpointKeys) {
  const auto file = ReadGolden("B/unet/diffusion_pytorch_model.safetensors");
  absl::StatusOr<UNet2DConditionModel> unet =
      LoadUNet(fd::testing::GoldenPath("B/unet"), torch::kCPU, torch::kFloat32);
  ASSERT_TRUE(unet.ok()) << unet.status();
  std::vector<std::string> keys = (*unet)->named_parameters().keys();
  std::sort(keys.begin(), keys.end());
  std::vector<std::string> expected;
  for (const auto& [key, unused] : file) expected.push_back(key);
  EXPECT_EQ(keys, expected);
  EXPECT_TRUE((*unet)->named_buffers().is_empty());
}

TEST(NetworkLoadingTest, MissingKeyIsListed) {
  CheckpointCopy copy("A/vae", "missing");
  copy.weights().erase("decoder.mid_block.attentions.0.to_q.weight");
  copy.weights().erase("encoder.conv_in.bias");
  copy.Write();
  absl::StatusOr<AutoencoderKL> vae = LoadVae(copy.dir(), torch::kCPU, torch::kFloat32);
  EXPECT_EQ(vae.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StrContains(vae.status().message(), "missing")) << vae.status();
  EXPECT_TRUE(
      absl::StrContains(vae.status().message(), "decoder.mid_block.attentions.0.to_q.weight"))
      << vae.status();
  EXPECT_TRUE(absl::StrContains(vae.status().message(), "encoder.conv_in.bias")) << vae.status();
}

TEST(NetworkLoadingTest, UnexpectedKeyIsListed) {
  CheckpointCopy copy("A/controlnet", "unexpected");
  copy.weights()["controlnet_down_blocks.99.weight"] = torch::zeros({16, 16, 1, 1});
  copy.Write();
  absl::StatusOr<ControlNetModel> controlnet =
      LoadControlNet(copy.dir(), torch::kCPU, torch::kFloat32);
  EXPECT_EQ(controlnet.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StrContains(controlnet.status().message(), "unexpected"))
      << controlnet.status();
  EXPECT_TRUE(absl::StrContains(controlnet.status().message(), "controlnet_down_blocks.99.weight"))
      << controlnet.status();
}

TEST(NetworkLoadingTest, ShapeMismatchIsListed) {
  CheckpointCopy copy("A/unet", "mismatch");
  copy.weights()["mid_block.resnets.0.conv1.weight"] = torch::zeros({32, 32, 1, 1});
  copy.Write();
  absl::StatusOr<UNet2DConditionModel> unet = LoadUNet(copy.dir(), torch::kCPU, torch::kFloat32);
  EXPECT_EQ(unet.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StrContains(unet.status().message(), "shape mismatch")) << unet.status();
  EXPECT_TRUE(absl::StrContains(unet.status().message(), "mid_block.resnets.0.conv1.weight"))
      << unet.status();
  EXPECT_TRUE(absl::StrContains(unet.status().message(), "[32, 32, 1, 1]")) << unet.status();
}

TEST(NetworkLoadingTest, ControlNetEncoderKindFollowsTheKeys) {
  // diffusers conditioning-embedding keys under a ControlNetModelEx config:
  // the keys decide the kind, so this loads as a diffusers ControlNet...
  CheckpointCopy copy("A/controlnet", "kind");
  copy.ReplaceConfig("\"ControlNetModel\"", "\"ControlNetModelEx\"");
  copy.Write();
  absl::StatusOr<ControlNetModel> controlnet =
      LoadControlNet(copy.dir(), torch::kCPU, torch::kFloat32);
  ASSERT_TRUE(controlnet.ok()) << controlnet.status();
  EXPECT_EQ((*controlnet)->embedding_kind(), ControlNetEmbeddingKind::kDiffusers);
  // ...while a mixture of both encoders' keys is a strict-loading error.
  copy.weights()["controlnet_cond_embedding.0.weight"] = torch::zeros({8, 10, 3, 3});
  copy.Write();
  controlnet = LoadControlNet(copy.dir(), torch::kCPU, torch::kFloat32);
  EXPECT_EQ(controlnet.status().code(), absl::StatusCode::kInvalidArgument);
}

TEST(NetworkLoadingTest, MissingFilesAreNotFound) {
  EXPECT_EQ(LoadVae("/nonexistent/vae", torch::kCPU, torch::kFloat32).status().code(),
            absl::StatusCode::kNotFound);
  CheckpointCopy copy("A/vae", "noweights");  // config.json only
  EXPECT_EQ(LoadVae(copy.dir(), torch::kCPU, torch::kFloat32).status().code(),
            absl::StatusCode::kNotFound);
}

TEST(NetworkLoadingTest, UnsupportedDtypeAndUnavailableDeviceAreRejected) {
  absl::StatusOr<AutoencoderKL> vae =
      LoadVae(fd::testing::GoldenPath("A/vae"), torch::kCPU, torch::kFloat64);
  EXPECT_EQ(vae.status().code(), absl::StatusCode::kInvalidArgument);
#if TORCH_VERSION_MAJOR < 2
  vae = LoadVae(fd::testing::GoldenPath("A/vae"), torch::kCPU, torch::kFloat16);
  EXPECT_EQ(vae.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StrContains(vae.status().message(), "float16")) << vae.status();
#endif
  if (!torch::cuda::is_available()) {
    vae =
        LoadVae(fd::testing::GoldenPath("A/vae"), torch::Device(torch::kCUDA, 0), torch::kFloat32);
    EXPECT_EQ(vae.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_TRUE(absl::StrContains(vae.status().message(), "CUDA")) << vae.status();
  }
}

// UNet2DConditionModelEx.add_extra_conditions: a base UNet's 4-channel
// conv_in is zero-padded to noisy latent + previous-frame latent.
TEST(NetworkLoadingTest, FourChannelConvInIsZeroPaddedToEight) {
  CheckpointCopy copy("A/unet", "conv_in4");
  copy.ReplaceConfig("\"in_channels\": 8", "\"in_channels\": 4");
  torch::Tensor full = copy.weights().at("conv_in.weight");  // [C0, 8, 3, 3]
  copy.weights()["conv_in.weight"] = full.slice(1, 0, 4).clone();
  copy.Write();

  absl::StatusOr<UNet2DConditionModel> padded = LoadUNet(copy.dir(), torch::kCPU, torch::kFloat32);
  ASSERT_TRUE(padded.ok()) << padded.status();
  EXPECT_EQ((*padded)->input_channels(), 8);
  EXPECT_TRUE(torch::equal((*padded)->conv_in->weight.slice(1, 0, 4), full.slice(1, 0, 4)));
  EXPECT_EQ((*padded)->conv_in->weight.slice(1, 4).abs().max().item<float>(), 0.0f);

  // The previous-frame latent then has no effect: same output as the golden
  // UNet with conv_in channels 4-7 zeroed.
  absl::StatusOr<UNet2DConditionModel> zeroed =
      LoadUNet(fd::testing::GoldenPath("A/unet"), torch::kCPU, torch::kFloat32);
  ASSERT_TRUE(zeroed.ok()) << zeroed.status();
  {
    torch::NoGradGuard no_grad;
    (*zeroed)->conv_in->weight.slice(1, 4).zero_();
  }
  const auto in = ReadGolden("A/golden/inputs.safetensors");
  torch::Tensor sample = GoldenTensor(ReadGolden("A/golden/unet.safetensors"), "sample");
  absl::StatusOr<torch::Tensor> a = (*padded)->Run(sample, GoldenTensor(in, "timestep"),
                                                   GoldenTensor(in, "encoder_hidden_states"));
  absl::StatusOr<torch::Tensor> b = (*zeroed)->Run(sample, GoldenTensor(in, "timestep"),
                                                   GoldenTensor(in, "encoder_hidden_states"));
  ASSERT_TRUE(a.ok()) << a.status();
  ASSERT_TRUE(b.ok()) << b.status();
  EXPECT_TRUE(torch::equal(*a, *b));

  // Without the FrameDiffuser input the base 4-channel UNet loads as is.
  absl::StatusOr<UNet2DConditionModel> base =
      LoadUNet(copy.dir(), torch::kCPU, torch::kFloat32, /*frame_diffuser_input=*/false);
  ASSERT_TRUE(base.ok()) << base.status();
  EXPECT_EQ((*base)->input_channels(), 4);
}

// bfloat16 on the CPU runs end to end and stays near the float32 golden
// (bf16 has ~3 significant digits; the tolerance is the bf16 class, not the
// float32 golden rule).
TEST(NetworkLoadingTest, BFloat16UNetRunsNearTheFloat32Golden) {
  absl::StatusOr<UNet2DConditionModel> unet =
      LoadUNet(fd::testing::GoldenPath("A/unet"), torch::kCPU, torch::kBFloat16);
  ASSERT_TRUE(unet.ok()) << unet.status();
  EXPECT_EQ((*unet)->conv_in->weight.scalar_type(), torch::kBFloat16);
  const auto in = ReadGolden("A/golden/inputs.safetensors");
  const auto golden = ReadGolden("A/golden/unet.safetensors");
  absl::StatusOr<torch::Tensor> out =
      (*unet)->Run(GoldenTensor(golden, "sample"), GoldenTensor(in, "timestep"),
                   GoldenTensor(in, "encoder_hidden_states"));
  ASSERT_TRUE(out.ok()) << out.status();
  EXPECT_EQ(out->scalar_type(), torch::kBFloat16);
  EXPECT_TRUE(fd::testing::TensorsClose(
      out->to(torch::kFloat32), GoldenTensor(golden, "noise_pred_without_controlnet"), 5e-2, 0.0));
}

}  // namespace
}  // namespace fd::model

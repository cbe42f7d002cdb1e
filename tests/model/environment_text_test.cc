// LoadEnvironment's text sources: the text-encoder route (text_encoder/ +
// tokenizer/, the prompt and negative prompt encoded once at load), the
// precedence of prompt_embeds.safetensors, and the errors. Environments are
// folders of symlinks: the tiny golden checkpoint (fd_pipeline/model) with
// the tiny golden CLIP text encoder (clip/) and the real SD1.5 tokenizer
// files. The widths come from the files: where the checkpoint's
// cross_attention_dim is not the encoder's hidden size (32 and 32 in the dev
// set; other golden sets differ), its UNet and ControlNet are rewritten at
// the encoder's width.
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <torch/torch.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "model/checkpoint/safetensors.h"
#include "model/networks/model_configs.h"
#include "model/pipeline/environment.h"
#include "model/pipeline/frame_pipeline.h"
#include "model/text/clip_text_model.h"
#include "model/text/clip_tokenizer.h"
#include "tests/testing/golden.h"
#include "tests/testing/tensor_matchers.h"

namespace fd::model {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;

// Other golden sets do not ship clip/tokenizer (clip/README.md): fall back to
// the build-time golden folder, as clip_text_model_test.cc does.
std::string TokenizerDir() {
  const std::string selected = fd::testing::GoldenPath("clip/tokenizer");
  if (fs::exists(selected + "/vocab.json")) return selected;
#ifdef FD_DEFAULT_GOLDEN_DIR
  return std::string(FD_DEFAULT_GOLDEN_DIR) + "/clip/tokenizer";
#else
  return selected;
#endif
}

class EnvironmentTextTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() /
           ("fd_environment_text_" +
            std::string(::testing::UnitTest::GetInstance()->current_test_info()->name()) + "_" +
            std::to_string(getpid()));
    fs::remove_all(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }

  // Links `parts` of `golden_model` (relative to the golden folder) into the
  // environment folder.
  void LinkNetworks(const std::string& golden_model, const std::vector<std::string>& parts) {
    const fs::path model = fs::absolute(fd::testing::GoldenPath(golden_model));
    for (const std::string& part : parts) fs::create_symlink(model / part, dir_ / part);
  }
  // The tiny checkpoint, its UNet and ControlNet at the text encoder's width.
  void LinkTinyNetworks() {
    LinkNetworks("fd_pipeline/model", {"vae", "scheduler", "controllora"});
    WriteNetworkOfWidth("fd_pipeline/model", "unet", TextWidth());
    WriteNetworkOfWidth("fd_pipeline/model", "controlnet", TextWidth());
  }

  // The golden CLIP text encoder's hidden size (its prompt embeddings' D).
  static int64_t TextWidth() {
    auto config = LoadCLIPTextConfig(fd::testing::GoldenPath("clip/text_encoder/config.json"));
    EXPECT_TRUE(config.ok()) << config.status();
    return config.ok() ? config->hidden_size : 0;
  }

  // `golden_model`/`part` (unet or controlnet) in the environment folder with
  // cross_attention_dim `width`: linked when it already has that width, else
  // written with config.json's cross_attention_dim and the attn2.to_k / to_v
  // weights (fresh values) of that width and every other tensor the golden's.
  // The ControlLoRA does not adapt to_k / to_v, so it still applies.
  void WriteNetworkOfWidth(const std::string& golden_model, const std::string& part,
                           int64_t width) {
    const fs::path from = fs::absolute(fd::testing::GoldenPath(golden_model)) / part;
    std::ifstream config_file(from / "config.json");
    std::stringstream text;
    text << config_file.rdbuf();
    nlohmann::json config = nlohmann::json::parse(text.str());
    nlohmann::json& dim = config["cross_attention_dim"];
    const bool same = dim.is_array() ? std::all_of(dim.begin(), dim.end(),
                                                   [&](const auto& d) { return d == width; })
                                     : dim == width;
    if (same) {
      fs::create_symlink(from, dir_ / part);
      return;
    }
    dim = width;
    auto tensors = LoadSafetensors((from / "diffusion_pytorch_model.safetensors").string());
    ASSERT_TRUE(tensors.ok()) << tensors.status();
    torch::manual_seed(width);
    for (auto& [key, tensor] : *tensors) {
      const bool key_or_value = key.find("attn2.to_k.weight") != std::string::npos ||
                                key.find("attn2.to_v.weight") != std::string::npos;
      if (key_or_value) {
        tensor = torch::randn({tensor.size(0), width}).to(tensor.scalar_type()) /
                 std::sqrt(static_cast<double>(width));
      }
    }
    fs::create_directories(dir_ / part);
    std::ofstream(dir_ / part / "config.json") << config.dump(2);
    ASSERT_TRUE(
        SaveSafetensors((dir_ / part / "diffusion_pytorch_model.safetensors").string(), *tensors)
            .ok());
  }
  void LinkTextEncoder() {
    fs::create_symlink(fs::absolute(fd::testing::GoldenPath("clip/text_encoder")),
                       dir_ / "text_encoder");
    fs::create_symlink(fs::absolute(TokenizerDir()), dir_ / "tokenizer");
  }
  void WriteSettings(const std::string& json) { std::ofstream(dir_ / "environment.json") << json; }

  // The prompt through the tokenizer and the CLIP text model directly:
  // padded to 77 tokens, last_hidden_state. [1, 77, H].
  static torch::Tensor EncodeDirectly(const std::string& prompt) {
    auto tokenizer = ClipTokenizer::FromDirectory(TokenizerDir());
    EXPECT_TRUE(tokenizer.ok()) << tokenizer.status();
    auto model = LoadClipTextModel(fd::testing::GoldenPath("clip/text_encoder"), torch::kCPU,
                                   torch::kFloat32);
    EXPECT_TRUE(model.ok()) << model.status();
    const ClipTokenizer::Encoding encoding = tokenizer->EncodePadded(prompt, 77);
    EXPECT_EQ(encoding.input_ids.size(), 77u);
    const torch::Tensor ids = torch::tensor(encoding.input_ids, torch::kInt64).unsqueeze(0);
    torch::InferenceMode inference_mode;
    auto embeds = (*model)->PromptEmbeds(ids);
    EXPECT_TRUE(embeds.ok()) << embeds.status();
    return embeds.ok() ? *embeds : torch::Tensor();
  }

  std::string dir() const { return dir_.string(); }

  fs::path dir_;
};

TEST_F(EnvironmentTextTest, TextEncoderEncodesThePromptsAtLoad) {
  LinkTinyNetworks();
  LinkTextEncoder();
  WriteSettings(R"({"prompt": "a photo of a cat", "negative_prompt": "lowres, blurry"})");
  ASSERT_FALSE(fs::exists(dir_ / "prompt_embeds.safetensors"));
  auto env = LoadEnvironment(dir());
  ASSERT_TRUE(env.ok()) << env.status();
  const torch::Tensor prompt = (*env)->prompt_embeds;
  ASSERT_TRUE(prompt.defined());
  EXPECT_EQ(prompt.sizes(), (std::vector<int64_t>{1, 77, TextWidth()}));
  EXPECT_EQ(prompt.scalar_type(), torch::kFloat32);
  EXPECT_EQ((*env)->unet->config().cross_attention_dim[0], prompt.size(2));
  // The load encodes [prompt, negative] as one batch; the direct runs are
  // batch 1 each, so allow float32 reduction-order noise.
  EXPECT_TRUE(fd::testing::TensorsClose(prompt, EncodeDirectly("a photo of a cat"), 0, 1e-5));
  ASSERT_TRUE((*env)->negative_prompt_embeds.defined());
  EXPECT_TRUE(fd::testing::TensorsClose((*env)->negative_prompt_embeds,
                                        EncodeDirectly("lowres, blurry"), 0, 1e-5));
  EXPECT_GT((prompt - (*env)->negative_prompt_embeds).abs().max().item<double>(), 1e-3);

  // The encoded prompts drive the pipeline, guidance > 1 included.
  FramePipeline pipeline(*env);
  PipelineInput r;
  r.condition = torch::zeros({1, 10, 32, 32});
  r.prev_latent = torch::zeros({1, 4, 4, 4});
  r.steps = 2;
  r.guidance_scale = 3.0;
  auto out = pipeline.Render({r});
  ASSERT_TRUE(out.ok()) << out.status();
  EXPECT_EQ((*out)[0].image_uint8.sizes(), (std::vector<int64_t>{32, 32, 3}));
}

// Without a negative prompt the unconditional embeddings are those of "",
// what diffusers encodes for classifier-free guidance.
TEST_F(EnvironmentTextTest, UnsetNegativePromptEncodesTheEmptyString) {
  LinkTinyNetworks();
  LinkTextEncoder();
  WriteSettings(R"({"prompt": "a street at night"})");
  auto env = LoadEnvironment(dir());
  ASSERT_TRUE(env.ok()) << env.status();
  EXPECT_TRUE(fd::testing::TensorsClose((*env)->prompt_embeds, EncodeDirectly("a street at night"),
                                        0, 1e-5));
  EXPECT_TRUE(
      fd::testing::TensorsClose((*env)->negative_prompt_embeds, EncodeDirectly(""), 0, 1e-5));
}

// prompt_embeds.safetensors wins over the text encoder when both exist.
TEST_F(EnvironmentTextTest, PromptEmbedsFileTakesPrecedence) {
  LinkTinyNetworks();
  LinkTextEncoder();
  // Embeddings of the networks' width (the golden file's matches only its own UNet).
  torch::manual_seed(7);
  ASSERT_TRUE(SaveSafetensors((dir_ / "prompt_embeds.safetensors").string(),
                              {{"prompt_embeds", torch::randn({1, 77, TextWidth()})}})
                  .ok());
  WriteSettings(R"({"prompt": "a photo of a cat"})");
  auto env = LoadEnvironment(dir());
  ASSERT_TRUE(env.ok()) << env.status();
  auto file = LoadPromptEmbeds(dir() + "/prompt_embeds.safetensors");
  ASSERT_TRUE(file.ok()) << file.status();
  EXPECT_TRUE(fd::testing::TensorsEqual((*env)->prompt_embeds, file->to(torch::kFloat32)));
  EXPECT_GT(((*env)->prompt_embeds - EncodeDirectly("a photo of a cat")).abs().max().item<double>(),
            1e-3);
}

TEST_F(EnvironmentTextTest, NoTextSourceIsNotFoundNamingBoth) {
  LinkTinyNetworks();
  auto env = LoadEnvironment(dir());
  ASSERT_FALSE(env.ok());
  EXPECT_EQ(env.status().code(), absl::StatusCode::kNotFound) << env.status();
  const std::string message(env.status().message());
  EXPECT_THAT(message, HasSubstr("prompt_embeds.safetensors"));
  EXPECT_THAT(message, HasSubstr("text_encoder"));
  EXPECT_THAT(message, HasSubstr("tokenizer"));

  // allow_missing_text: loads, without prompt embeddings; a request without
  // its own embeddings is then refused.
  EnvironmentOptions options;
  options.allow_missing_text = true;
  env = LoadEnvironment(dir(), options);
  ASSERT_TRUE(env.ok()) << env.status();
  EXPECT_FALSE((*env)->prompt_embeds.defined());
  FramePipeline pipeline(*env);
  PipelineInput r;
  r.condition = torch::zeros({1, 10, 32, 32});
  r.prev_latent = torch::zeros({1, 4, 4, 4});
  EXPECT_EQ(pipeline.Begin({r}).status().code(), absl::StatusCode::kFailedPrecondition);
}

// A text encoder without its tokenizer (or the reverse) names what is missing.
TEST_F(EnvironmentTextTest, HalfATextEncoderIsNamed) {
  LinkTinyNetworks();
  fs::create_symlink(fs::absolute(fd::testing::GoldenPath("clip/text_encoder")),
                     dir_ / "text_encoder");
  auto env = LoadEnvironment(dir());
  ASSERT_FALSE(env.ok());
  EXPECT_EQ(env.status().code(), absl::StatusCode::kNotFound) << env.status();
  EXPECT_THAT(std::string(env.status().message()), HasSubstr("tokenizer"));
}

// A text encoder whose hidden size is not the UNet's cross_attention_dim
// (the tiny checkpoint rewritten 8 wider than the encoder).
TEST_F(EnvironmentTextTest, TextEncoderWidthMismatchIsNamed) {
  const int64_t unet_width = TextWidth() + 8;
  LinkNetworks("fd_pipeline/model", {"vae", "scheduler"});
  WriteNetworkOfWidth("fd_pipeline/model", "unet", unet_width);
  WriteNetworkOfWidth("fd_pipeline/model", "controlnet", unet_width);
  LinkTextEncoder();
  EnvironmentOptions options;
  options.lora_policy = LoraPolicy::kSkip;
  auto env = LoadEnvironment(dir(), options);
  ASSERT_FALSE(env.ok());
  EXPECT_EQ(env.status().code(), absl::StatusCode::kInvalidArgument) << env.status();
  const std::string message(env.status().message());
  EXPECT_THAT(message, HasSubstr("cross_attention_dim"));
  EXPECT_THAT(message, HasSubstr(absl::StrCat("[1, T, ", unet_width, "]")));
  EXPECT_THAT(message, HasSubstr("text_encoder"));
}

}  // namespace
}  // namespace fd::model

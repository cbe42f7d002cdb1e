// LoadEnvironment's text sources: the text-encoder route (text_encoder/ +
// tokenizer/, the prompt and negative prompt encoded once at load), the
// precedence of prompt_embeds.safetensors, and the errors. Environments are
// folders of symlinks: the tiny golden checkpoint (fd_pipeline/model, UNet
// cross_attention_dim 32) with the tiny golden CLIP text encoder (clip/,
// hidden size 32) and the real SD1.5 tokenizer files.
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <torch/torch.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "model/clip_text_model.h"
#include "model/clip_tokenizer.h"
#include "model/environment.h"
#include "model/frame_pipeline.h"
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
  void LinkTinyNetworks() {
    LinkNetworks("fd_pipeline/model", {"unet", "vae", "controlnet", "scheduler", "controllora"});
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
  EXPECT_EQ(prompt.sizes(), (std::vector<int64_t>{1, 77, 32}));
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
  FrameRequest r;
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
  LinkNetworks("fd_pipeline/model", {"prompt_embeds.safetensors"});
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
  FrameRequest r;
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

// A text encoder whose hidden size (32) is not the UNet's cross_attention_dim
// (config B: 40).
TEST_F(EnvironmentTextTest, TextEncoderWidthMismatchIsNamed) {
  LinkNetworks("B", {"unet", "vae", "controlnet", "scheduler"});
  LinkTextEncoder();
  EnvironmentOptions options;
  options.lora_policy = LoraPolicy::kSkip;
  auto env = LoadEnvironment(dir(), options);
  ASSERT_FALSE(env.ok());
  EXPECT_EQ(env.status().code(), absl::StatusCode::kInvalidArgument) << env.status();
  const std::string message(env.status().message());
  EXPECT_THAT(message, HasSubstr("cross_attention_dim"));
  EXPECT_THAT(message, HasSubstr("[1, T, 40]"));
  EXPECT_THAT(message, HasSubstr("text_encoder"));
}

}  // namespace
}  // namespace fd::model

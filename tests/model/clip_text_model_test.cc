// Tests for model/text/clip_text_model.h against clip/golden/text_encoder.safetensors
// (transformers 4.30 CLIPTextModel, tiny random config): every output and
// intermediate within the golden tolerance, the tokenizer -> encoder path, the
// precomputed prompt_embeds path and the error cases.
#include "model/text/clip_text_model.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <torch/torch.h>

#include <algorithm>
#include <cstdlib>
#include <fstream>
#include <iostream>
#include <limits>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "absl/strings/match.h"
#include "model/checkpoint/safetensors.h"
#include "model/text/clip_tokenizer.h"
#include "tests/testing/golden.h"
#include "tests/testing/tensor_matchers.h"

namespace fd::model {
namespace {

using ::testing::HasSubstr;

// Golden acceptance (clip/README.md): max|out - ref| <= 1e-4 max|ref| + 1e-6.
void ExpectGolden(const std::string& name, const torch::Tensor& actual,
                  const torch::Tensor& expected) {
  EXPECT_TRUE(fd::testing::TensorsClose(actual, expected, 1e-4, 1e-6)) << name;
  if (actual.defined() && expected.defined() && actual.sizes() == expected.sizes()) {
    const double err =
        (actual.to(torch::kFloat64) - expected.to(torch::kFloat64)).abs().max().item<double>();
    const double ref = expected.abs().max().item<double>();
    std::cout << "[golden] clip/" << name << " max_abs_err=" << err << " rel=" << err / ref << "\n";
  }
}

bool Exists(const std::string& path) { return std::ifstream(path).good(); }

std::string TokenizerDir() {
  const std::string selected = fd::testing::GoldenPath("clip/tokenizer");
  if (Exists(selected + "/vocab.json")) return selected;
#ifdef FD_DEFAULT_GOLDEN_DIR
  return std::string(FD_DEFAULT_GOLDEN_DIR) + "/clip/tokenizer";
#else
  return selected;
#endif
}

class ClipTextModelGoldenTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    auto model = LoadClipTextModel(fd::testing::GoldenPath("clip/text_encoder"), torch::kCPU,
                                   torch::kFloat32);
    ASSERT_TRUE(model.ok()) << model.status();
    model_ = new ClipTextModel(*model);
    auto file =
        SafetensorsFile::Open(fd::testing::GoldenPath("clip/golden/text_encoder.safetensors"));
    ASSERT_TRUE(file.ok()) << file.status();
    golden_ = new std::map<std::string, torch::Tensor>();
    for (const std::string& key : (*file)->Keys()) (*golden_)[key] = *(*file)->Get(key);
    metadata_ = new std::map<std::string, std::string>((*file)->metadata());
  }
  static void TearDownTestSuite() {
    delete model_;
    delete golden_;
    delete metadata_;
  }
  static const torch::Tensor& G(const std::string& key) {
    static const torch::Tensor kMissing;
    auto it = golden_->find(key);
    EXPECT_NE(it, golden_->end()) << "missing golden tensor " << key;
    return it == golden_->end() ? kMissing : it->second;
  }

  static ClipTextModel* model_;
  static std::map<std::string, torch::Tensor>* golden_;
  static std::map<std::string, std::string>* metadata_;
};
ClipTextModel* ClipTextModelGoldenTest::model_ = nullptr;
std::map<std::string, torch::Tensor>* ClipTextModelGoldenTest::golden_ = nullptr;
std::map<std::string, std::string>* ClipTextModelGoldenTest::metadata_ = nullptr;

TEST_F(ClipTextModelGoldenTest, ParameterNamesAreTheTransformersStateDict) {
  auto file = SafetensorsFile::Open(fd::testing::GoldenPath("clip/text_encoder/model.safetensors"));
  ASSERT_TRUE(file.ok());
  std::vector<std::string> names;
  for (const auto& p : (*model_)->named_parameters()) names.push_back(p.key());
  for (const auto& b : (*model_)->named_buffers()) names.push_back(b.key());
  std::sort(names.begin(), names.end());
  EXPECT_EQ(names, (*file)->Keys());
}

TEST_F(ClipTextModelGoldenTest, OutputsAndIntermediatesMatch) {
  DebugTaps taps;
  auto out = (*model_)->Run(G("input_ids"), &taps);
  ASSERT_TRUE(out.ok()) << out.status();
  ExpectGolden("last_hidden_state", out->last_hidden_state, G("last_hidden_state"));
  ExpectGolden("pooler_output", out->pooler_output, G("pooler_output"));
  int hidden = 0;
  for (size_t i = 0; golden_->count("hidden_states." + std::to_string(i)); ++i, ++hidden) {
    ASSERT_LT(i, out->hidden_states.size());
    ExpectGolden("hidden_states." + std::to_string(i), out->hidden_states[i],
                 G("hidden_states." + std::to_string(i)));
  }
  EXPECT_EQ(hidden, static_cast<int>(out->hidden_states.size()));
  int debug = 0;
  for (const auto& [key, value] : *golden_) {
    if (!absl::StartsWith(key, "debug.")) continue;
    const std::string name = key.substr(6);
    ASSERT_TRUE(taps.count(name)) << "no tap " << name;
    ExpectGolden(key, taps[name], value);
    ++debug;
  }
  EXPECT_GT(debug, 0);
}

TEST_F(ClipTextModelGoldenTest, ClipSkipAndUnpaddedRun) {
  auto skip = (*model_)->PromptEmbeds(G("input_ids"), 1);
  ASSERT_TRUE(skip.ok()) << skip.status();
  ExpectGolden("clip_skip1.prompt_embeds", *skip, G("clip_skip1.prompt_embeds"));
  auto unpadded = (*model_)->Run(G("input_ids_unpadded"));
  ASSERT_TRUE(unpadded.ok()) << unpadded.status();
  ExpectGolden("unpadded.last_hidden_state", unpadded->last_hidden_state,
               G("unpadded.last_hidden_state"));
  ExpectGolden("unpadded.pooler_output", unpadded->pooler_output, G("unpadded.pooler_output"));
}

TEST_F(ClipTextModelGoldenTest, PromptsThroughTokenizerAndEncoder) {
  auto tokenizer = ClipTokenizer::FromDirectory(TokenizerDir());
  ASSERT_TRUE(tokenizer.ok()) << tokenizer.status();
  ASSERT_TRUE(metadata_->count("prompts"));
  const auto prompts =
      nlohmann::json::parse((*metadata_)["prompts"]).get<std::vector<std::string>>();
  auto ids = tokenizer->EncodeBatch(prompts);
  ASSERT_TRUE(ids.ok());
  EXPECT_TRUE(fd::testing::TensorsEqual(*ids, G("input_ids")));
  ASSERT_TRUE(metadata_->count("unpadded_prompt"));
  const std::vector<int64_t> unpadded = tokenizer->Encode((*metadata_)["unpadded_prompt"]);
  EXPECT_TRUE(
      fd::testing::TensorsEqual(torch::tensor(unpadded).unsqueeze(0), G("input_ids_unpadded")));
  auto embeds = EncodePrompts(*tokenizer, *model_, prompts);
  ASSERT_TRUE(embeds.ok()) << embeds.status();
  ExpectGolden("EncodePrompts", *embeds, G("last_hidden_state"));
}

TEST_F(ClipTextModelGoldenTest, RejectsBadInputIds) {
  const int64_t max_len = (*model_)->config().max_position_embeddings;
  const int64_t vocab = (*model_)->config().vocab_size;
  auto floats = (*model_)->Run(torch::zeros({1, 4}));
  EXPECT_EQ(floats.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(floats.status().message(), HasSubstr("input_ids"));
  EXPECT_EQ((*model_)->Run(torch::zeros({1, 2, 3}, torch::kInt64)).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_THAT((*model_)->Run(torch::zeros({1, max_len + 1}, torch::kInt64)).status().message(),
              HasSubstr("max_position_embeddings"));
  EXPECT_THAT((*model_)->Run(torch::full({1, 3}, vocab, torch::kInt64)).status().message(),
              HasSubstr("ids must be in"));
  EXPECT_THAT((*model_)->Run(torch::full({1, 3}, -1, torch::kInt64)).status().message(),
              HasSubstr("ids must be in"));
  EXPECT_EQ((*model_)->PromptEmbeds(G("input_ids"), -1).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(
      (*model_)
          ->PromptEmbeds(G("input_ids"), static_cast<int>((*model_)->config().num_hidden_layers))
          .status()
          .code(),
      absl::StatusCode::kInvalidArgument);
}

TEST(ClipTextModelLoadTest, AcceptsCheckpointsWithoutPositionIdsAndRejectsBrokenOnes) {
  const std::string src = fd::testing::GoldenPath("clip/text_encoder");
  auto tensors = LoadSafetensors(src + "/model.safetensors");
  ASSERT_TRUE(tensors.ok());
  const std::string dir = ::testing::TempDir() + "/h4_clip_no_position_ids";
  ASSERT_EQ(std::system(
                ("mkdir -p '" + dir + "' && cp '" + src + "/config.json' '" + dir + "/'").c_str()),
            0);
  auto without = *tensors;
  without.erase("text_model.embeddings.position_ids");
  ASSERT_TRUE(SaveSafetensors(dir + "/model.safetensors", without).ok());
  auto model = LoadClipTextModel(dir, torch::kCPU, torch::kFloat32);
  EXPECT_TRUE(model.ok()) << model.status();

  auto broken = *tensors;
  broken.erase("text_model.final_layer_norm.weight");
  ASSERT_TRUE(SaveSafetensors(dir + "/model.safetensors", broken).ok());
  auto missing = LoadClipTextModel(dir, torch::kCPU, torch::kFloat32);
  EXPECT_EQ(missing.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(missing.status().message(), HasSubstr("final_layer_norm.weight"));

  EXPECT_EQ(LoadClipTextModel("/nonexistent", torch::kCPU, torch::kFloat32).status().code(),
            absl::StatusCode::kNotFound);
}

TEST(PromptEmbedsTest, LoadsThePrecomputedEmbeddingAndRejectsBadFiles) {
  auto embeds =
      LoadPromptEmbeds(fd::testing::GoldenPath("fd_pipeline/model/prompt_embeds.safetensors"));
  ASSERT_TRUE(embeds.ok()) << embeds.status();
  auto inputs =
      LoadSafetensors(fd::testing::GoldenPath("fd_pipeline/golden/e2e_inputs.safetensors"));
  ASSERT_TRUE(inputs.ok());
  EXPECT_TRUE(fd::testing::TensorsEqual(*embeds, inputs->at("prompt_embeds")));

  EXPECT_EQ(LoadPromptEmbeds("/nonexistent.safetensors").status().code(),
            absl::StatusCode::kNotFound);
  const std::string path = ::testing::TempDir() + "/h4_bad_prompt_embeds.safetensors";
  torch::Tensor nan = torch::zeros({1, 4, 8});
  nan[0][1][2] = std::numeric_limits<float>::quiet_NaN();
  ASSERT_TRUE(SaveSafetensors(path, {{"prompt_embeds", nan}}).ok());
  EXPECT_THAT(LoadPromptEmbeds(path).status().message(), HasSubstr("NaN"));
  ASSERT_TRUE(SaveSafetensors(path, {{"prompt_embeds", torch::zeros({4}, torch::kInt64)}}).ok());
  EXPECT_EQ(LoadPromptEmbeds(path).status().code(), absl::StatusCode::kInvalidArgument);
  ASSERT_TRUE(
      SaveSafetensors(path, {{"a", torch::zeros({2, 3})}, {"b", torch::zeros({2, 3})}}).ok());
  EXPECT_THAT(LoadPromptEmbeds(path).status().message(), HasSubstr("prompt_embeds"));
}

}  // namespace
}  // namespace fd::model

// Tests for model/lora_file.{h,cc}: parsing the golden LoRA / ControlLoRA
// files (PEFT and diffusers key formats), the merged-weight delta against the
// goldens' merged weights, and every kind of malformed file.
#include "model/lora/lora_file.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <torch/torch.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <set>
#include <string>

#include "model/checkpoint/safetensors.h"
#include "tests/testing/golden.h"
#include "tests/testing/tensor_matchers.h"

namespace fd::model {
namespace {

using ::testing::AllOf;
using ::testing::HasSubstr;

std::string Message(const absl::Status& status) { return std::string(status.message()); }

bool EndsWith(const std::string& text, const std::string& suffix) {
  return text.size() >= suffix.size() &&
         text.compare(text.size() - suffix.size(), suffix.size(), suffix) == 0;
}

// lora_info.json (a golden-set description of the adapter, not a diffusers
// file): rank, lora_alpha and the adapted modules.
nlohmann::json ReadLoraInfo(const std::string& relative) {
  std::ifstream in(fd::testing::GoldenPath(relative));
  EXPECT_TRUE(in.good()) << relative;
  return nlohmann::json::parse(in, nullptr, /*allow_exceptions=*/false);
}

void ExpectMatchesLoraInfo(const LoraWeights& lora, const std::string& info_path) {
  const nlohmann::json info = ReadLoraInfo(info_path);
  ASSERT_TRUE(info.is_object()) << info_path;
  std::set<std::string> expected_modules;
  for (const auto& module : info.at("target_modules")) {
    expected_modules.insert(module.get<std::string>());
  }
  std::set<std::string> modules;
  for (const auto& [module, weights] : lora.modules) {
    modules.insert(module);
    EXPECT_EQ(weights.rank, info.at("rank").get<int64_t>()) << module;
    EXPECT_DOUBLE_EQ(weights.alpha, info.at("lora_alpha").get<double>()) << module;
    EXPECT_DOUBLE_EQ(weights.scaling(), info.at("scaling").get<double>()) << module;
  }
  EXPECT_EQ(modules, expected_modules);
}

// The raw file tensor behind each parsed half.
void ExpectHalvesAreFileTensors(const LoraWeights& lora, const SafetensorsFile& file) {
  for (const auto& [module, weights] : lora.modules) {
    SCOPED_TRACE(module);
    const std::string peft_a = "unet." + module + ".lora_A.weight";
    const std::string diffusers_a = "unet." + module + ".lora.down.weight";
    const bool peft = file.Contains(peft_a);
    ASSERT_TRUE(peft || file.Contains(diffusers_a));
    const auto a = file.Get(peft ? peft_a : diffusers_a);
    const auto b =
        file.Get(peft ? "unet." + module + ".lora_B.weight" : "unet." + module + ".lora.up.weight");
    ASSERT_TRUE(a.ok() && b.ok());
    EXPECT_TRUE(fd::testing::TensorsEqual(weights.down, *a));
    EXPECT_TRUE(fd::testing::TensorsEqual(weights.up, *b));
  }
}

TEST(LoraFileGoldenTest, ConfigBPeftKeys) {
  const std::string path = fd::testing::GoldenPath("B/unet_lora/pytorch_lora_weights.safetensors");
  auto lora = LoadLoraWeights(path);
  ASSERT_TRUE(lora.ok()) << lora.status();
  EXPECT_EQ(lora->source, path);
  ExpectMatchesLoraInfo(*lora, "B/unet_lora/lora_info.json");
  auto file = SafetensorsFile::Open(path);
  ASSERT_TRUE(file.ok()) << file.status();
  EXPECT_EQ(lora->modules.size() * 2, (*file)->Keys().size());  // no alpha keys
  ExpectHalvesAreFileTensors(*lora, **file);
  // full_skip_attn: no attention projections.
  for (const auto& [module, weights] : lora->modules) {
    EXPECT_THAT(module, ::testing::Not(HasSubstr(".to_q")));
  }
}

TEST(LoraFileGoldenTest, ConfigAMixesPeftAndDiffusersKeys) {
  const std::string path = fd::testing::GoldenPath("A/unet_lora/pytorch_lora_weights.safetensors");
  auto lora = LoadLoraWeights(path);
  ASSERT_TRUE(lora.ok()) << lora.status();
  ExpectMatchesLoraInfo(*lora, "A/unet_lora/lora_info.json");
  auto file = SafetensorsFile::Open(path);
  ASSERT_TRUE(file.ok()) << file.status();
  ExpectHalvesAreFileTensors(*lora, **file);
  int attention_projections = 0;
  for (const auto& [module, weights] : lora->modules) {
    if (EndsWith(module, ".to_q") || EndsWith(module, ".to_out.0")) {
      ++attention_projections;
      EXPECT_FALSE(weights.is_conv());
      EXPECT_TRUE((*file)->Contains("unet." + module + ".lora.down.weight")) << module;
    }
  }
  EXPECT_GT(attention_projections, 0);
}

TEST(LoraFileGoldenTest, FrameDiffuserControlLoras) {
  const std::string dir = fd::testing::GoldenPath("fd_pipeline/model/controllora");
  int files = 0;
  for (const auto& entry : std::filesystem::directory_iterator(dir)) {
    if (entry.path().extension() != ".safetensors") continue;
    ++files;
    SCOPED_TRACE(entry.path().string());
    auto lora = LoadLoraWeights(entry.path().string());
    ASSERT_TRUE(lora.ok()) << lora.status();
    auto file = SafetensorsFile::Open(entry.path().string());
    ASSERT_TRUE(file.ok()) << file.status();
    ExpectHalvesAreFileTensors(*lora, **file);
    EXPECT_EQ(lora->modules.size() * 2, (*file)->Keys().size());
    // conv_in's adapter covers the 8-channel input (noisy + previous latent).
    ASSERT_EQ(lora->modules.count("conv_in"), 1u);
    const LoraModuleWeights& conv_in = lora->modules.at("conv_in");
    EXPECT_TRUE(conv_in.is_conv());
    EXPECT_EQ(conv_in.WeightShape(), (std::vector<int64_t>{conv_in.up.size(0), 8, 3, 3}));
    for (const auto& [module, weights] : lora->modules) {
      EXPECT_DOUBLE_EQ(weights.scaling(), 1.0) << module;  // alpha = r (no alpha keys)
    }
  }
  EXPECT_GT(files, 0);
}

TEST(LoraFileGoldenTest, FilesWithoutUnetPrefixParseTheSame) {
  const std::string path = fd::testing::GoldenPath("A/unet_lora/pytorch_lora_weights.safetensors");
  auto tensors = LoadSafetensors(path);
  ASSERT_TRUE(tensors.ok()) << tensors.status();
  std::map<std::string, torch::Tensor> unprefixed;
  for (const auto& [key, tensor] : *tensors) unprefixed[key.substr(5)] = tensor;
  auto with_prefix = ParseLoraWeights(*tensors, path);
  auto without_prefix = ParseLoraWeights(unprefixed, "unprefixed");
  ASSERT_TRUE(with_prefix.ok()) << with_prefix.status();
  ASSERT_TRUE(without_prefix.ok()) << without_prefix.status();
  ASSERT_EQ(with_prefix->modules.size(), without_prefix->modules.size());
  for (const auto& [module, weights] : with_prefix->modules) {
    ASSERT_EQ(without_prefix->modules.count(module), 1u) << module;
    EXPECT_TRUE(weights.down.is_same(without_prefix->modules.at(module).down));
  }
}

// merged = base + LoraDelta(scale) for the goldens' merged weights. Keys:
// `merged_weight.scale<s>.<module>.weight` (A/B) or `merged_weight.<module>.
// weight` (fd_pipeline, scale 1).
void CheckMergedWeights(const std::string& golden, const std::string& base_weights,
                        const std::string& lora_path) {
  auto merged = SafetensorsFile::Open(fd::testing::GoldenPath(golden));
  auto base = SafetensorsFile::Open(fd::testing::GoldenPath(base_weights));
  auto lora = LoadLoraWeights(fd::testing::GoldenPath(lora_path));
  ASSERT_TRUE(merged.ok()) << merged.status();
  ASSERT_TRUE(base.ok()) << base.status();
  ASSERT_TRUE(lora.ok()) << lora.status();
  const std::string prefix = "merged_weight.";
  const std::string suffix = ".weight";
  int checked = 0;
  for (const std::string& key : (*merged)->Keys()) {
    if (key.rfind(prefix, 0) != 0) continue;
    std::string name = key.substr(prefix.size());  // [scale<s>.]<module>.weight
    double scale = 1.0;
    if (name.rfind("scale", 0) == 0) {
      // "scale1.0.<module>.weight": the number runs to the second dot.
      const size_t first_dot = name.find('.');
      const size_t second_dot = name.find('.', first_dot + 1);
      scale = std::stod(name.substr(5, second_dot - 5));
      name = name.substr(second_dot + 1);
    }
    ASSERT_GT(name.size(), suffix.size());
    const std::string module = name.substr(0, name.size() - suffix.size());
    SCOPED_TRACE(key);
    ASSERT_EQ(lora->modules.count(module), 1u) << module;
    auto weight = (*base)->Get(module + ".weight");
    ASSERT_TRUE(weight.ok()) << weight.status();
    auto delta = LoraDelta(lora->modules.at(module), scale);
    ASSERT_TRUE(delta.ok()) << delta.status();
    EXPECT_EQ(delta->sizes(), weight->sizes());
    EXPECT_EQ(lora->modules.at(module).WeightShape(), weight->sizes().vec());
    const ::testing::AssertionResult close =
        fd::testing::TensorsClose(*weight + *delta, *(*merged)->Get(key));
    EXPECT_TRUE(close);
    // The error report (max abs diff, ratio) lands in --gtest_output=xml.
    ::testing::Test::RecordProperty(key, close.message());
    ++checked;
  }
  EXPECT_GT(checked, 0);
}

TEST(LoraFileGoldenTest, DeltaReproducesConfigAMergedWeights) {
  CheckMergedWeights("A/golden/unet_lora.safetensors", "A/unet/diffusion_pytorch_model.safetensors",
                     "A/unet_lora/pytorch_lora_weights.safetensors");
}

TEST(LoraFileGoldenTest, DeltaReproducesConfigBMergedWeights) {
  CheckMergedWeights("B/golden/unet_lora.safetensors", "B/unet/diffusion_pytorch_model.safetensors",
                     "B/unet_lora/pytorch_lora_weights.safetensors");
}

TEST(LoraFileGoldenTest, DeltaReproducesFrameDiffuserMergedWeights) {
  CheckMergedWeights("fd_pipeline/golden/lora_merge.safetensors",
                     "fd_pipeline/model/unet/diffusion_pytorch_model.safetensors",
                     "fd_pipeline/model/controllora/pytorch_lora_weights.safetensors");
  // n_merged_modules: how many modules the reference merged.
  auto merged =
      SafetensorsFile::Open(fd::testing::GoldenPath("fd_pipeline/golden/lora_merge.safetensors"));
  auto lora = LoadLoraWeights(
      fd::testing::GoldenPath("fd_pipeline/model/controllora/pytorch_lora_weights.safetensors"));
  ASSERT_TRUE(merged.ok() && lora.ok());
  EXPECT_EQ(static_cast<int64_t>(lora->modules.size()),
            (*merged)->Get("n_merged_modules")->item<int64_t>());
}

// ---------------------------------------------------------------------------
// Delta math against independent formulations.

TEST(LoraDeltaTest, LinearIsScaledBTimesA) {
  torch::manual_seed(11);
  LoraModuleWeights weights;
  weights.down = torch::randn({3, 5}, torch::kFloat64);
  weights.up = torch::randn({7, 3}, torch::kFloat64);
  weights.rank = 3;
  weights.alpha = 6.0;  // scaling 2
  auto delta = LoraDelta(weights, 0.5);
  ASSERT_TRUE(delta.ok()) << delta.status();
  torch::Tensor expected = torch::zeros({7, 5}, torch::kFloat64);
  for (int64_t o = 0; o < 7; ++o) {
    for (int64_t i = 0; i < 5; ++i) {
      for (int64_t r = 0; r < 3; ++r) expected[o][i] += weights.up[o][r] * weights.down[r][i];
    }
  }
  EXPECT_TRUE(fd::testing::TensorsClose(*delta, expected * (0.5 * 2.0), 1e-12, 1e-12));
  EXPECT_EQ(weights.WeightShape(), (std::vector<int64_t>{7, 5}));
}

TEST(LoraDeltaTest, ConvMatchesPeftConvFormulation) {
  // PEFT's get_delta_weight for k x k convs:
  // conv2d(A.permute(1, 0, 2, 3), B).permute(1, 0, 2, 3) * scaling.
  torch::manual_seed(12);
  LoraModuleWeights weights;
  weights.down = torch::randn({4, 6, 3, 3});
  weights.up = torch::randn({5, 4, 1, 1});
  weights.rank = 4;
  weights.alpha = 4.0;
  auto delta = LoraDelta(weights, 1.0);
  ASSERT_TRUE(delta.ok()) << delta.status();
  EXPECT_EQ(delta->scalar_type(), torch::kFloat32);
  const torch::Tensor peft =
      torch::conv2d(weights.down.permute({1, 0, 2, 3}), weights.up).permute({1, 0, 2, 3});
  EXPECT_TRUE(fd::testing::TensorsClose(*delta, peft.contiguous()));
  EXPECT_EQ(weights.WeightShape(), (std::vector<int64_t>{5, 6, 3, 3}));

  // Half-precision adapters are computed in float32.
  LoraModuleWeights half = weights;
  half.down = weights.down.to(torch::kFloat16);
  half.up = weights.up.to(torch::kFloat16);
  auto half_delta = LoraDelta(half, 2.0);
  ASSERT_TRUE(half_delta.ok()) << half_delta.status();
  EXPECT_EQ(half_delta->scalar_type(), torch::kFloat32);
  EXPECT_TRUE(fd::testing::TensorsClose(*half_delta, *delta * 2.0, 2e-3, 1e-3));
}

TEST(LoraDeltaTest, RejectsInconsistentAdapters) {
  LoraModuleWeights weights;
  weights.down = torch::ones({4, 6});
  weights.up = torch::ones({5, 3});
  weights.rank = 4;
  EXPECT_EQ(LoraDelta(weights).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(LoraDelta(LoraModuleWeights{}).status().code(), absl::StatusCode::kInvalidArgument);
}

// ---------------------------------------------------------------------------
// Malformed files.

void ExpectParseError(const std::map<std::string, torch::Tensor>& tensors,
                      const std::vector<std::string>& named) {
  const auto lora = ParseLoraWeights(tensors, "bad_lora.safetensors");
  ASSERT_FALSE(lora.ok());
  EXPECT_EQ(lora.status().code(), absl::StatusCode::kInvalidArgument) << lora.status();
  EXPECT_THAT(Message(lora.status()), HasSubstr("bad_lora.safetensors"));
  for (const std::string& name : named) EXPECT_THAT(Message(lora.status()), HasSubstr(name));
}

TEST(LoraFileErrorTest, MissingPartnerNamesTheKey) {
  ExpectParseError({{"unet.conv_in.lora_A.weight", torch::ones({4, 8, 3, 3})}},
                   {"unet.conv_in.lora_A.weight", "conv_in.lora_B.weight", "missing"});
  ExpectParseError({{"unet.mid.to_q.lora.up.weight", torch::ones({16, 4})}},
                   {"unet.mid.to_q.lora.up.weight", "mid.to_q.lora.down.weight"});
  ExpectParseError({{"unet.fc.alpha", torch::tensor(4.0)}}, {"unet.fc.alpha"});
}

TEST(LoraFileErrorTest, InconsistentShapes) {
  // Rank mismatch.
  ExpectParseError(
      {{"fc.lora_A.weight", torch::ones({4, 8})}, {"fc.lora_B.weight", torch::ones({16, 3})}},
      {"fc.lora_A.weight", "rank mismatch"});
  // Conv up projection must be 1x1.
  ExpectParseError({{"conv.lora_A.weight", torch::ones({4, 8, 3, 3})},
                    {"conv.lora_B.weight", torch::ones({16, 4, 3, 3})}},
                   {"conv.lora_A.weight", "[16, 4, 3, 3]"});
  // Mixed dimensionality.
  ExpectParseError(
      {{"fc.lora_A.weight", torch::ones({4, 8})}, {"fc.lora_B.weight", torch::ones({16, 4, 1, 1})}},
      {"fc.lora_A.weight"});
  // Integer weights.
  ExpectParseError({{"fc.lora_A.weight", torch::ones({4, 8}, torch::kInt64)},
                    {"fc.lora_B.weight", torch::ones({16, 4})}},
                   {"fc.lora_A.weight", "floating point"});
  // Alpha must be a single number.
  ExpectParseError({{"fc.lora_A.weight", torch::ones({4, 8})},
                    {"fc.lora_B.weight", torch::ones({16, 4})},
                    {"fc.alpha", torch::ones({2})}},
                   {"fc.alpha"});
}

TEST(LoraFileErrorTest, UnknownAndForeignKeys) {
  ExpectParseError({{"unet.fc.lora_B.bias", torch::ones({16})}}, {"unet.fc.lora_B.bias"});
  ExpectParseError(
      {{"lora_unet_down_blocks_0_resnets_0_conv1.lora_down.weight", torch::ones({4, 8, 3, 3})}},
      {"lora_unet_down_blocks_0_resnets_0_conv1.lora_down.weight"});
  ExpectParseError({{"text_encoder.text_model.fc1.lora_A.weight", torch::ones({4, 8})}},
                   {"text_encoder", "not supported"});
}

TEST(LoraFileErrorTest, DuplicateOrMixedFormatsForOneModule) {
  ExpectParseError({{"unet.fc.lora_A.weight", torch::ones({4, 8})},
                    {"fc.lora_A.weight", torch::ones({4, 8})},
                    {"fc.lora_B.weight", torch::ones({16, 4})}},
                   {"already has this weight"});
  ExpectParseError(
      {{"fc.lora.down.weight", torch::ones({4, 8})}, {"fc.lora_B.weight", torch::ones({16, 4})}},
      {"mixes"});
}

TEST(LoraFileErrorTest, ExplicitAlphaChangesTheScaling) {
  auto lora = ParseLoraWeights({{"fc.lora_A.weight", torch::ones({4, 8})},
                                {"fc.lora_B.weight", torch::ones({16, 4})},
                                {"fc.alpha", torch::tensor(8.0)}},
                               "alpha.safetensors");
  ASSERT_TRUE(lora.ok()) << lora.status();
  const LoraModuleWeights& fc = lora->modules.at("fc");
  EXPECT_EQ(fc.rank, 4);
  EXPECT_DOUBLE_EQ(fc.alpha, 8.0);
  EXPECT_DOUBLE_EQ(fc.scaling(), 2.0);
  auto delta = LoraDelta(fc, 0.5);
  ASSERT_TRUE(delta.ok());
  // B@A of ones = 4 everywhere; * 0.5 * 2.
  EXPECT_TRUE(fd::testing::TensorsEqual(*delta, torch::full({16, 8}, 4.0f)));
}

TEST(LoraFileErrorTest, MissingAndCorruptFiles) {
  const std::string missing = ::testing::TempDir() + "/no_such_lora.safetensors";
  EXPECT_EQ(LoadLoraWeights(missing).status().code(), absl::StatusCode::kNotFound);
  const std::string corrupt =
      ::testing::TempDir() + "/fd_lora_test_corrupt_" + std::to_string(::getpid()) + ".safetensors";
  std::ofstream(corrupt, std::ios::binary) << "not a safetensors file";
  const auto status = LoadLoraWeights(corrupt).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(Message(status), HasSubstr(corrupt));
  std::filesystem::remove(corrupt);
}

}  // namespace
}  // namespace fd::model

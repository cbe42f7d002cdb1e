// Tests for model/state_dict_loader.{h,cc} with a small hand-built module:
// exact loading with dtype conversion, strict error reports (missing,
// unexpected, shape and dtype mismatches, truncation), the module staying
// unchanged on error, and the rename / adapt_shape / allow hooks.
#include "model/checkpoint/state_dict_loader.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <sys/stat.h>
#include <torch/torch.h>
#include <unistd.h>

#include <map>
#include <string>

#include "model/checkpoint/safetensors.h"
#include "tests/testing/tensor_matchers.h"

namespace fd::model {
namespace {

using ::testing::AllOf;
using ::testing::HasSubstr;
using ::testing::Not;

std::string TempPath(const std::string& name) {
  static const std::string dir = [] {
    std::string path = ::testing::TempDir() + "/fd_state_dict_test_" + std::to_string(::getpid());
    ::mkdir(path.c_str(), 0700);
    return path;
  }();
  return dir + "/" + name;
}

// A nested module with Linear, Conv2d, LayerNorm parameters and buffers.
struct BlockImpl : torch::nn::Module {
  BlockImpl() {
    norm = register_module("norm", torch::nn::LayerNorm(torch::nn::LayerNormOptions({4})));
    conv = register_module("conv", torch::nn::Conv2d(torch::nn::Conv2dOptions(2, 5, 3)));
  }
  torch::nn::LayerNorm norm{nullptr};
  torch::nn::Conv2d conv{nullptr};
};
TORCH_MODULE(Block);

struct TinyNetImpl : torch::nn::Module {
  TinyNetImpl() {
    fc = register_module("fc", torch::nn::Linear(3, 4));
    block = register_module("block", Block());
    steps = register_buffer("steps", torch::zeros({2}, torch::kInt64));
    scale = register_buffer("scale", torch::ones({4}));
  }
  torch::nn::Linear fc{nullptr};
  Block block{nullptr};
  torch::Tensor steps;
  torch::Tensor scale;
};
TORCH_MODULE(TinyNet);

std::map<std::string, torch::Tensor> RandomStateDict(TinyNet& net, uint64_t seed) {
  torch::manual_seed(seed);
  std::map<std::string, torch::Tensor> state;
  for (const auto& item : net->named_parameters()) {
    state[item.key()] = torch::randn(item.value().sizes());
  }
  state["steps"] = torch::tensor({7, 11}, torch::kInt64);
  state["scale"] = torch::rand({4});
  return state;
}

std::map<std::string, torch::Tensor> Snapshot(torch::nn::Module& module) {
  std::map<std::string, torch::Tensor> values;
  for (const auto& item : module.named_parameters()) values[item.key()] = item.value().clone();
  for (const auto& item : module.named_buffers()) values[item.key()] = item.value().clone();
  return values;
}

void ExpectModuleEquals(torch::nn::Module& module,
                        const std::map<std::string, torch::Tensor>& expected) {
  const auto actual = Snapshot(module);
  ASSERT_EQ(actual.size(), expected.size());
  for (const auto& [name, value] : expected) {
    ASSERT_EQ(actual.count(name), 1u) << name;
    EXPECT_TRUE(fd::testing::TensorsEqual(actual.at(name), value)) << name;
  }
}

std::string Message(const absl::Status& status) { return std::string(status.message()); }

TEST(StateDictLoaderTest, LoadsEveryParameterAndBufferFromAFile) {
  TinyNet net;
  const auto state = RandomStateDict(net, 1);
  const std::string path = TempPath("tiny.safetensors");
  ASSERT_TRUE(SaveSafetensors(path, state).ok());
  auto file = SafetensorsFile::Open(path);
  ASSERT_TRUE(file.ok()) << file.status();

  ASSERT_TRUE(LoadStateDict(*net, **file).ok());
  ExpectModuleEquals(*net, state);
  // Loading copies: the parameters are still the module's own tensors.
  EXPECT_TRUE(net->fc->weight.requires_grad());
  EXPECT_TRUE(net->named_parameters()["fc.weight"].is_same(net->fc->weight));
}

TEST(StateDictLoaderTest, ConvertsToTheModuleDtype) {
  TinyNet net;
  auto state = RandomStateDict(net, 2);
  std::map<std::string, torch::Tensor> half = state;
  for (auto& [name, tensor] : half) {
    if (tensor.is_floating_point()) tensor = tensor.to(torch::kFloat16);
  }
  const std::string path = TempPath("tiny_f16.safetensors");
  ASSERT_TRUE(SaveSafetensors(path, half).ok());
  auto file = SafetensorsFile::Open(path);
  ASSERT_TRUE(file.ok()) << file.status();

  // float32 module <- F16 file.
  ASSERT_TRUE(LoadStateDict(*net, **file).ok());
  EXPECT_EQ(net->fc->weight.scalar_type(), torch::kFloat32);
  EXPECT_TRUE(fd::testing::TensorsEqual(net->fc->weight, half["fc.weight"].to(torch::kFloat32)));

  // float64 module <- float32 map.
  // (Module::to(dtype) would also turn the int64 buffer into float64, which
  // the loader rightly refuses to fill from integers: convert the floats only.)
  TinyNet net64;
  for (torch::Tensor& parameter : net64->parameters()) {
    parameter.set_data(parameter.to(torch::kFloat64));
  }
  net64->scale.set_data(net64->scale.to(torch::kFloat64));
  const absl::Status status64 = LoadStateDict(*net64, state);
  ASSERT_TRUE(status64.ok()) << status64;
  EXPECT_EQ(net64->block->conv->weight.scalar_type(), torch::kFloat64);
  EXPECT_TRUE(fd::testing::TensorsEqual(net64->block->conv->weight,
                                        state["block.conv.weight"].to(torch::kFloat64)));
  EXPECT_TRUE(fd::testing::TensorsEqual(net64->steps, state["steps"]));
}

TEST(StateDictLoaderTest, ReportsAllProblemsAndLeavesTheModuleUnchanged) {
  TinyNet net;
  const auto before = Snapshot(*net);
  auto state = RandomStateDict(net, 3);
  state.erase("fc.bias");
  state.erase("block.norm.weight");
  state["block.extra.weight"] = torch::ones({2});
  state["unused"] = torch::ones({1});
  state["block.conv.weight"] = torch::ones({5, 3, 3, 3});  // module: [5, 2, 3, 3]
  state["steps"] = torch::ones({2});                       // float into an int64 buffer

  const absl::Status status = LoadStateDict(*net, state, {}, "bad checkpoint");
  ASSERT_EQ(status.code(), absl::StatusCode::kInvalidArgument) << status;
  const std::string message = Message(status);
  EXPECT_THAT(message, HasSubstr("bad checkpoint"));
  EXPECT_THAT(message, HasSubstr("2 missing keys: [block.norm.weight, fc.bias]"));
  EXPECT_THAT(message, HasSubstr("2 unexpected keys: [block.extra.weight, unused]"));
  EXPECT_THAT(message,
              HasSubstr("1 shape mismatch: [block.conv.weight: checkpoint [5, 3, 3, 3] vs module "
                        "[5, 2, 3, 3]]"));
  EXPECT_THAT(message, HasSubstr("1 dtype mismatch: [steps: checkpoint Float vs module Long]"));
  ExpectModuleEquals(*net, before);
}

TEST(StateDictLoaderTest, ErrorFromAFileNamesThePath) {
  TinyNet net;
  auto state = RandomStateDict(net, 4);
  state.erase("scale");
  const std::string path = TempPath("missing_scale.safetensors");
  ASSERT_TRUE(SaveSafetensors(path, state).ok());
  auto file = SafetensorsFile::Open(path);
  ASSERT_TRUE(file.ok()) << file.status();
  const absl::Status status = LoadStateDict(*net, **file);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(Message(status), AllOf(HasSubstr(path), HasSubstr("1 missing key: [scale]")));
}

TEST(StateDictLoaderTest, LongListsAreTruncated) {
  torch::nn::Sequential many;
  for (int i = 0; i < 30; ++i) many->push_back(torch::nn::Linear(2, 2));  // 60 parameters
  LoadOptions options;
  options.max_listed = 5;
  const absl::Status status = LoadStateDict(*many, std::map<std::string, torch::Tensor>{}, options);
  ASSERT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(Message(status), HasSubstr("60 missing keys: [0.bias, 0.weight, 1.bias, 1.weight, "
                                         "10.bias, ... and 55 more]"));
}

TEST(StateDictLoaderTest, RenameHookMapsAndDropsKeys) {
  TinyNet net;
  const auto state = RandomStateDict(net, 5);
  std::map<std::string, torch::Tensor> prefixed;
  for (const auto& [name, tensor] : state) prefixed["unet." + name] = tensor;
  prefixed["text_encoder.weight"] = torch::ones({1});

  LoadOptions options;
  options.rename_key = [](const std::string& key) -> std::string {
    if (key.rfind("unet.", 0) == 0) return key.substr(5);
    return "";  // drop everything else
  };
  ASSERT_TRUE(LoadStateDict(*net, prefixed, options).ok());
  ExpectModuleEquals(*net, state);

  // Without the hook every key is unexpected (reported by checkpoint name).
  const absl::Status status = LoadStateDict(*net, prefixed);
  EXPECT_THAT(Message(status), HasSubstr("unet.fc.weight"));

  // Two keys mapping to one target are an error.
  options.rename_key = [](const std::string& key) {
    return key.rfind("unet.", 0) == 0 ? key.substr(5) : std::string("fc.bias");
  };
  EXPECT_THAT(Message(LoadStateDict(*net, prefixed, options)), HasSubstr("both map to 'fc.bias'"));
}

TEST(StateDictLoaderTest, AdaptShapeHookZeroPadsConvInput) {
  // The UNet loader's use: a [5, 1, 3, 3] conv weight zero-padded to the
  // module's [5, 2, 3, 3] (add_extra_conditions).
  TinyNet net;
  auto state = RandomStateDict(net, 6);
  const torch::Tensor narrow = state["block.conv.weight"].slice(1, 0, 1).clone();
  state["block.conv.weight"] = narrow;

  int calls = 0;
  LoadOptions options;
  options.adapt_shape = [&calls](const std::string& name, torch::Tensor loaded,
                                 const torch::Tensor& target) -> absl::StatusOr<torch::Tensor> {
    ++calls;
    EXPECT_EQ(name, "block.conv.weight");
    torch::Tensor padded = torch::zeros(target.sizes(), loaded.options());
    padded.slice(1, 0, loaded.size(1)).copy_(loaded);
    return padded;
  };
  ASSERT_TRUE(LoadStateDict(*net, state, options).ok());
  EXPECT_EQ(calls, 1);  // only for the mismatching tensor
  EXPECT_TRUE(fd::testing::TensorsEqual(net->block->conv->weight.slice(1, 0, 1), narrow));
  EXPECT_EQ(net->block->conv->weight.slice(1, 1, 2).abs().max().item<float>(), 0.0f);

  // A hook that cannot help leaves a shape mismatch; a hook error is returned.
  options.adapt_shape = [](const std::string&, torch::Tensor loaded,
                           const torch::Tensor&) -> absl::StatusOr<torch::Tensor> {
    return loaded;
  };
  EXPECT_THAT(Message(LoadStateDict(*net, state, options)),
              HasSubstr("block.conv.weight: checkpoint [5, 1, 3, 3] vs module [5, 2, 3, 3]"));
  options.adapt_shape = [](const std::string& name, torch::Tensor,
                           const torch::Tensor&) -> absl::StatusOr<torch::Tensor> {
    return absl::FailedPreconditionError("cannot adapt " + name);
  };
  const absl::Status status = LoadStateDict(*net, state, options);
  EXPECT_EQ(status.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(Message(status), HasSubstr("cannot adapt block.conv.weight"));
}

TEST(StateDictLoaderTest, AllowMissingAndIgnoreUnexpected) {
  TinyNet net;
  const torch::Tensor scale_before = net->scale.clone();
  auto state = RandomStateDict(net, 7);
  state.erase("scale");
  state["position_ids"] = torch::arange(4);
  LoadOptions options;
  options.allow_missing = [](const std::string& name) { return name == "scale"; };
  options.ignore_unexpected = [](const std::string& key) { return key == "position_ids"; };
  ASSERT_TRUE(LoadStateDict(*net, state, options).ok());
  EXPECT_TRUE(fd::testing::TensorsEqual(net->scale, scale_before));
  EXPECT_TRUE(fd::testing::TensorsEqual(net->fc->weight, state["fc.weight"]));
}

TEST(StateDictLoaderTest, UndefinedTensorInMapIsAnError) {
  TinyNet net;
  auto state = RandomStateDict(net, 8);
  state["fc.weight"] = torch::Tensor();
  const absl::Status status = LoadStateDict(*net, state);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(Message(status), AllOf(HasSubstr("fc.weight"), HasSubstr("undefined")));
  EXPECT_THAT(Message(status), Not(HasSubstr("missing")));
}

}  // namespace
}  // namespace fd::model

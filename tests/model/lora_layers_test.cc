// LoraLinear / LoraConv2d and ApplyLora: live and merged adapters agree, the
// live scale can be changed, adapters stay out of named_parameters(), and
// LoRA files that do not fit the network are rejected with every problem
// listed and nothing changed.
#include "model/lora/lora_layers.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <string>

#include "absl/strings/match.h"
#include "model/lora/apply_lora.h"
#include "model/lora/lora_file.h"
#include "tests/testing/tensor_matchers.h"

namespace fd::model {
namespace {

using fd::testing::TensorsClose;

// A small network: "proj" (Linear 6->5) and "block.conv" (3x3 Conv2d 3->4,
// stride 2, padding 1), with random weights.
class TinyNetImpl : public torch::nn::Module {
 public:
  TinyNetImpl() {
    proj = register_module("proj", LoraLinear(6, 5));
    block = register_module("block", std::make_shared<torch::nn::Module>());
    conv = block->register_module("conv", LoraConv2d(3, 4, 3, 2, 1));
    torch::NoGradGuard no_grad;
    for (auto& p : parameters()) p.copy_(torch::randn(p.sizes()));
  }
  std::shared_ptr<torch::nn::Module> block;
  LoraLinear proj{nullptr};
  LoraConv2d conv{nullptr};
};
TORCH_MODULE(TinyNet);

LoraWeights TinyLora() {
  LoraWeights lora;
  lora.source = "tiny";
  LoraModuleWeights linear;
  linear.down = torch::randn({2, 6});
  linear.up = torch::randn({5, 2});
  linear.rank = 2;
  linear.alpha = 4.0;  // scaling 2
  lora.modules["proj"] = linear;
  LoraModuleWeights conv;
  conv.down = torch::randn({2, 3, 3, 3});
  conv.up = torch::randn({4, 2, 1, 1});
  conv.rank = 2;
  conv.alpha = 2.0;
  lora.modules["block.conv"] = conv;
  return lora;
}

class LoraLayersTest : public ::testing::Test {
 protected:
  void SetUp() override { torch::manual_seed(7); }
};

TEST_F(LoraLayersTest, LayersMatchTorchModules) {
  TinyNet net;
  torch::Tensor x = torch::randn({2, 6});
  EXPECT_TRUE(TensorsClose(net->proj(x), torch::linear(x, net->proj->weight, net->proj->bias)));
  torch::Tensor image = torch::randn({1, 3, 9, 7});
  torch::Tensor y = net->conv(image);
  EXPECT_EQ(y.sizes(), (std::vector<int64_t>{1, 4, 5, 4}));
  EXPECT_TRUE(TensorsClose(y, torch::conv2d(image, net->conv->weight, net->conv->bias, 2, 1)));
  std::vector<std::string> keys = net->named_parameters().keys();
  EXPECT_EQ(keys, (std::vector<std::string>{"proj.weight", "proj.bias", "block.conv.weight",
                                            "block.conv.bias"}));
}

TinyNet CopyOf(TinyNet& source) {
  TinyNet copy;
  torch::NoGradGuard no_grad;
  auto from = source->named_parameters();
  for (auto& item : copy->named_parameters()) item.value().copy_(from[item.key()]);
  return copy;
}

TEST_F(LoraLayersTest, LiveEqualsMergedAndFollowsTheScale) {
  const LoraWeights lora = TinyLora();
  TinyNet base;
  TinyNet live = CopyOf(base), merged = CopyOf(base), merged_half = CopyOf(base);
  ASSERT_TRUE(ApplyLora(*live, lora, LoraMode::kLive, 1.0).ok());
  ASSERT_TRUE(ApplyLora(*merged, lora, LoraMode::kMerged, 1.0).ok());
  ASSERT_TRUE(ApplyLora(*merged_half, lora, LoraMode::kMerged, 0.5).ok());

  // Merged weights: W + scale * alpha/r * B@A (Linear), the einsum (conv).
  const LoraModuleWeights& p = lora.modules.at("proj");
  EXPECT_TRUE(
      TensorsClose(merged->proj->weight, base->proj->weight + 2.0 * torch::matmul(p.up, p.down)));
  EXPECT_TRUE(TensorsClose(merged->proj->bias, base->proj->bias));
  const LoraModuleWeights& c = lora.modules.at("block.conv");
  EXPECT_TRUE(
      TensorsClose(merged->conv->weight,
                   base->conv->weight +
                       torch::einsum("or,rihw->oihw", {c.up.select(3, 0).select(2, 0), c.down})));

  torch::Tensor x = torch::randn({3, 6});
  torch::Tensor image = torch::randn({2, 3, 8, 6});
  // PEFT: base(x) + lora_B(lora_A(x)) * scaling.
  torch::Tensor expected_linear =
      base->proj(x) + torch::linear(torch::linear(x, p.down), p.up) * 2.0;
  EXPECT_TRUE(TensorsClose(live->proj(x), expected_linear));
  EXPECT_TRUE(TensorsClose(merged->proj(x), expected_linear));
  EXPECT_TRUE(TensorsClose(live->conv(image), merged->conv(image)));
  EXPECT_FALSE(TensorsClose(live->conv(image), base->conv(image)));

  SetLoraScale(*live, 0.5);
  EXPECT_TRUE(TensorsClose(live->proj(x), merged_half->proj(x)));
  EXPECT_TRUE(TensorsClose(live->conv(image), merged_half->conv(image)));
  // Merged adapters ignore the live scale.
  SetLoraScale(*merged, 0.0);
  EXPECT_TRUE(TensorsClose(merged->proj(x), expected_linear));
  RemoveLiveLora(*live);
  EXPECT_TRUE(TensorsClose(live->proj(x), base->proj(x)));
}

TEST_F(LoraLayersTest, LiveAdaptersAreNotParametersAndFollowTheModuleDtype) {
  TinyNet net;
  const std::vector<std::string> keys = net->named_parameters().keys();
  ASSERT_TRUE(ApplyLora(*net, TinyLora(), LoraMode::kLive, 1.0).ok());
  EXPECT_EQ(net->named_parameters().keys(), keys);
  EXPECT_TRUE(net->named_buffers().is_empty());
  EXPECT_TRUE(net->proj->has_live_adapters());
  net->to(torch::kFloat64);
  torch::Tensor y = net->proj(torch::randn({1, 6}, torch::kFloat64));
  EXPECT_EQ(y.scalar_type(), torch::kFloat64);
}

TEST_F(LoraLayersTest, UnmatchedAndMisfitAdaptersAreListedAndNothingChanges) {
  TinyNet net;
  TinyNet original = CopyOf(net);
  LoraWeights lora = TinyLora();
  lora.modules["down_blocks.9.nothing"] = lora.modules.at("proj");
  lora.modules["block"] = lora.modules.at("proj");               // a module, but no Linear/Conv2d
  lora.modules["block.conv"].down = torch::randn({2, 3, 1, 1});  // kernel 1 != 3
  for (LoraMode mode : {LoraMode::kMerged, LoraMode::kLive}) {
    absl::Status status = ApplyLora(*net, lora, mode, 1.0);
    EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
    EXPECT_TRUE(absl::StrContains(status.message(), "down_blocks.9.nothing")) << status;
    EXPECT_TRUE(absl::StrContains(status.message(), "block;") ||
                absl::StrContains(status.message(), "block."))
        << status;
    EXPECT_TRUE(absl::StrContains(status.message(), "block.conv:")) << status;
    EXPECT_TRUE(absl::StrContains(status.message(), "tiny")) << status;
  }
  EXPECT_FALSE(net->proj->has_live_adapters());
  EXPECT_FALSE(net->conv->has_live_adapters());
  for (const auto& item : net->named_parameters()) {
    EXPECT_TRUE(torch::equal(item.value(), original->named_parameters()[item.key()])) << item.key();
  }
}

}  // namespace
}  // namespace fd::model

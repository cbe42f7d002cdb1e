// model/networks/gradient_checkpoint.h: a checkpointed function gives the
// plain call's values and gradients, runs again in backward only, and the
// UNet / ControlNet blocks checkpoint (and still train identically) when the
// flag is on.
#include "model/networks/gradient_checkpoint.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <memory>
#include <set>
#include <string>
#include <vector>

#include "model/networks/controlnet.h"
#include "model/networks/model_configs.h"
#include "model/networks/unet.h"
#include "model/presets/presets.h"
#include "model/presets/training_init.h"

namespace fd::model {
namespace {

// Counts the CheckpointFunction nodes of the graph that produced `output`.
int CountCheckpointNodes(const torch::Tensor& output) {
  int count = 0;
  std::vector<torch::autograd::Node*> stack = {output.grad_fn().get()};
  std::set<torch::autograd::Node*> seen;
  while (!stack.empty()) {
    torch::autograd::Node* node = stack.back();
    stack.pop_back();
    if (node == nullptr || !seen.insert(node).second) continue;
    if (node->name().find("CheckpointFunction") != std::string::npos) ++count;
    for (const torch::autograd::Edge& edge : node->next_edges())
      stack.push_back(edge.function.get());
  }
  return count;
}

// A two-input function with parameters and a non-linearity, so that its
// backward needs the activations the checkpoint drops.
struct SmallNet {
  torch::nn::Linear first{torch::nn::LinearOptions(6, 5)};
  torch::nn::Linear second{torch::nn::LinearOptions(5, 3)};
  int calls = 0;

  torch::Tensor operator()(const std::vector<torch::Tensor>& in) {
    ++calls;
    torch::Tensor h = torch::gelu(first(in[0])) * torch::sigmoid(in[1]);
    if (in.size() > 2 && in[2].defined()) h = h + in[2];
    return torch::tanh(second(h));
  }
};

TEST(CheckpointTest, SameValuesAndGradientsAsThePlainCall) {
  torch::manual_seed(1);
  auto net = std::make_shared<SmallNet>();
  const torch::Tensor x0 = torch::randn({4, 6});
  const torch::Tensor y0 = torch::randn({4, 5});
  const torch::Tensor weights = torch::randn({4, 3});

  auto run = [&](bool checkpoint) {
    for (torch::Tensor& p : net->first->parameters()) p.mutable_grad() = torch::Tensor();
    for (torch::Tensor& p : net->second->parameters()) p.mutable_grad() = torch::Tensor();
    torch::Tensor x = x0.clone().requires_grad_(true);
    torch::Tensor y = y0.clone().requires_grad_(true);
    // The third input is undefined: it stays undefined inside the function.
    std::vector<torch::Tensor> inputs = {x, y, torch::Tensor()};
    torch::Tensor out = checkpoint
                            ? Checkpoint([net](const auto& in) { return (*net)(in); }, inputs)
                            : (*net)(inputs);
    EXPECT_EQ(CountCheckpointNodes(out), checkpoint ? 1 : 0);
    (out * weights).sum().backward();
    return std::vector<torch::Tensor>{out.detach(), x.grad(), y.grad(),
                                      net->first->weight.grad().clone(),
                                      net->second->bias.grad().clone()};
  };
  const std::vector<torch::Tensor> plain = run(false);
  net->calls = 0;
  const std::vector<torch::Tensor> checkpointed = run(true);
  EXPECT_EQ(net->calls, 2);  // the forward, then the recomputation in backward
  ASSERT_EQ(plain.size(), checkpointed.size());
  EXPECT_TRUE(torch::equal(plain[0], checkpointed[0]));
  for (size_t i = 1; i < plain.size(); ++i) {
    ASSERT_TRUE(checkpointed[i].defined()) << i;
    EXPECT_TRUE(torch::allclose(plain[i], checkpointed[i], 1e-6, 1e-7)) << i;
  }
}

TEST(CheckpointTest, WithoutGradModeOrInputGradientsItIsAPlainCall) {
  auto net = std::make_shared<SmallNet>();
  const torch::Tensor x = torch::randn({2, 6});
  const torch::Tensor y = torch::randn({2, 5});
  auto fn = [net](const auto& in) { return (*net)(in); };
  {
    torch::NoGradGuard no_grad;
    torch::Tensor out = Checkpoint(fn, {x.clone().requires_grad_(true), y});
    EXPECT_FALSE(out.requires_grad());
    EXPECT_EQ(net->calls, 1);
  }
  // No input needs a gradient but the parameters do: no checkpoint node
  // (it would cut the parameters off), and the parameters get gradients.
  torch::Tensor out = Checkpoint(fn, {x, y});
  EXPECT_EQ(CountCheckpointNodes(out), 0);
  out.sum().backward();
  ASSERT_TRUE(net->first->weight.grad().defined());
  EXPECT_GT(net->first->weight.grad().abs().sum().item<double>(), 0.0);
}

struct TinyPair {
  UNet2DConditionModel unet{nullptr};
  ControlNetModel controlnet{nullptr};
};

TinyPair MakeTinyPair() {
  TinyPair pair;
  absl::StatusOr<PresetConfigs> configs = GetPresetConfigs("tiny");
  EXPECT_TRUE(configs.ok()) << configs.status();
  absl::StatusOr<UNet2DConditionConfig> config = ParseUNet2DConditionConfig(configs->unet, "tiny");
  EXPECT_TRUE(config.ok()) << config.status();
  absl::StatusOr<UNet2DConditionModel> unet = MakeUNet(*config);
  EXPECT_TRUE(unet.ok()) << unet.status();
  pair.unet = *unet;
  EXPECT_TRUE(InitializeDefaultWeights(*pair.unet, 4).ok());
  absl::StatusOr<std::string> cn_json =
      ControlNetConfigJsonFromUNet(configs->unet, {8, 16, 16, 32});
  EXPECT_TRUE(cn_json.ok()) << cn_json.status();
  absl::StatusOr<ControlNetConfig> cn_config = ParseControlNetConfig(*cn_json, "derived");
  EXPECT_TRUE(cn_config.ok()) << cn_config.status();
  absl::StatusOr<ControlNetModel> controlnet = ControlNetFromUNet(*pair.unet, *cn_config, 2);
  EXPECT_TRUE(controlnet.ok()) << controlnet.status();
  pair.controlnet = *controlnet;
  // Trained-looking weights: the zero convs of a fresh ControlNet would give
  // its inner blocks no gradient.
  torch::NoGradGuard no_grad;
  for (torch::Tensor& p : pair.controlnet->parameters()) p.add_(torch::randn_like(p) * 0.05);
  return pair;
}

TEST(GradientCheckpointingTest, UNetAndControlNetTrainIdenticallyWithItOn) {
  torch::manual_seed(7);
  TinyPair pair = MakeTinyPair();
  torch::manual_seed(3);
  const torch::Tensor noisy = torch::randn({2, 4, 8, 8});
  const torch::Tensor t = torch::tensor({10, 900});
  const torch::Tensor embeds = torch::randn({2, 7, 32});
  const torch::Tensor cond = torch::rand({2, 10, 64, 64}) * 2 - 1;
  const torch::Tensor target = torch::randn({2, 4, 8, 8});

  struct Result {
    torch::Tensor output;
    int checkpoint_nodes = 0;
    std::vector<torch::Tensor> grads;  // every parameter of both, then the input's
  };
  auto step = [&](bool enabled) {
    EXPECT_GT(SetGradientCheckpointing(*pair.unet, enabled), 0);
    EXPECT_GT(SetGradientCheckpointing(*pair.controlnet, enabled), 0);
    pair.unet->zero_grad();
    pair.controlnet->zero_grad();
    Result result;
    torch::Tensor sample = noisy.clone().requires_grad_(true);
    std::vector<torch::Tensor> residuals = pair.controlnet->forward(sample, t, embeds, cond);
    result.output = pair.unet->forward(sample, t, embeds, residuals);
    result.checkpoint_nodes = CountCheckpointNodes(result.output);
    torch::mse_loss(result.output, target).backward();
    auto grad_of = [](const torch::Tensor& p) {
      return p.grad().defined() ? p.grad().clone() : torch::zeros_like(p);
    };
    for (const torch::Tensor& p : pair.unet->parameters()) result.grads.push_back(grad_of(p));
    for (const torch::Tensor& p : pair.controlnet->parameters()) result.grads.push_back(grad_of(p));
    result.grads.push_back(sample.grad().clone());
    result.output = result.output.detach();
    return result;
  };
  const Result plain = step(false);
  const Result checkpointed = step(true);
  EXPECT_EQ(plain.checkpoint_nodes, 0);
  // Every resnet of the down and up blocks, the mid block's second, and the
  // transformer blocks, of both networks.
  EXPECT_GT(checkpointed.checkpoint_nodes, 6);
  EXPECT_TRUE(torch::equal(plain.output, checkpointed.output));
  ASSERT_EQ(plain.grads.size(), checkpointed.grads.size());
  int nonzero = 0;
  for (size_t i = 0; i < plain.grads.size(); ++i) {
    EXPECT_TRUE(torch::allclose(plain.grads[i], checkpointed.grads[i], 1e-5, 1e-7)) << i;
    nonzero += plain.grads[i].abs().sum().item<double>() > 0 ? 1 : 0;
  }
  EXPECT_GT(nonzero, static_cast<int>(plain.grads.size()) / 2);

  // Inference with the flag on is the plain inference forward (no
  // recomputation). Inference runs the G-buffer encoder channels-last
  // (model/runtime/conv2d_kernel.h), so it equals the training forward only
  // within float32 rounding.
  torch::NoGradGuard no_grad;
  auto infer = [&] {
    std::vector<torch::Tensor> residuals = pair.controlnet->forward(noisy, t, embeds, cond);
    return pair.unet->forward(noisy, t, embeds, residuals);
  };
  const torch::Tensor with_flag = infer();
  SetGradientCheckpointing(*pair.unet, false);
  SetGradientCheckpointing(*pair.controlnet, false);
  EXPECT_TRUE(torch::equal(with_flag, infer()));
  EXPECT_TRUE(torch::allclose(with_flag, plain.output, 1e-5, 1e-6));
}

}  // namespace
}  // namespace fd::model

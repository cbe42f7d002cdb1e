// BatchInvariantScope: thread-local, nesting, and LoraConv2d / LoraLinear
// running each sample of a batch as a batch of one inside it (with and
// without live LoRA adapters), so that a sample's result is bitwise its
// result alone.
#include "model/runtime/batch_invariance.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <thread>
#include <vector>

#include "model/lora/lora_layers.h"

namespace fd::model {
namespace {

TEST(BatchInvariantScopeTest, IsThreadLocalAndNests) {
  EXPECT_FALSE(BatchInvariantScope::Active());
  {
    BatchInvariantScope off(/*enabled=*/false);
    EXPECT_FALSE(BatchInvariantScope::Active());
  }
  {
    BatchInvariantScope on;
    EXPECT_TRUE(BatchInvariantScope::Active());
    {
      // A disabled inner scope leaves the outer one in force.
      BatchInvariantScope off(/*enabled=*/false);
      EXPECT_TRUE(BatchInvariantScope::Active());
    }
    bool other_thread = true;
    std::thread([&] { other_thread = BatchInvariantScope::Active(); }).join();
    EXPECT_FALSE(other_thread);
    EXPECT_TRUE(BatchInvariantScope::Active());
  }
  EXPECT_FALSE(BatchInvariantScope::Active());
}

// Each sample of `batch` through `layer` alone, concatenated.
template <typename Layer>
torch::Tensor SampleBySample(Layer& layer, const torch::Tensor& batch) {
  std::vector<torch::Tensor> out;
  for (int64_t i = 0; i < batch.size(0); ++i)
    out.push_back(layer->forward(batch.slice(0, i, i + 1)));
  return torch::cat(out, 0);
}

// Shapes of the UNet's layers at small latents (3x3 convolutions of 32
// channels on 8x8, attention projections of 80 tokens, the time embedding's
// one row per sample), where oneDNN and OpenBLAS pick other kernels for
// other batch sizes.
class BatchInvariantLayersTest : public ::testing::Test {
 protected:
  void SetUp() override {
    torch::manual_seed(11);
    torch::NoGradGuard no_grad;
    for (torch::nn::Module* m :
         std::vector<torch::nn::Module*>{conv.get(), linear.get(), time_linear.get()}) {
      for (auto& p : m->parameters()) p.copy_(torch::randn(p.sizes()) * 0.1);
    }
    // A live adapter on the convolution (rank 4), as with the authors' LoRA.
    ASSERT_TRUE(conv->AddLiveAdapter(torch::randn({4, 32, 3, 3}) * 0.1,
                                     torch::randn({32, 4, 1, 1}) * 0.1, /*scaling=*/2.0)
                    .ok());
  }
  LoraConv2d conv{32, 32, 3, 1, 1};
  LoraLinear linear{128, 512};
  LoraLinear time_linear{128, 512};
};

TEST_F(BatchInvariantLayersTest, EachSampleIsBitwiseItsResultAlone) {
  torch::InferenceMode inference_mode;
  const torch::Tensor images = torch::randn({5, 32, 8, 8});
  const torch::Tensor tokens = torch::randn({5, 80, 128});
  const torch::Tensor rows = torch::randn({5, 128});
  BatchInvariantScope scope;
  EXPECT_TRUE(torch::equal(conv->forward(images), SampleBySample(conv, images)));
  EXPECT_TRUE(torch::equal(linear->forward(tokens), SampleBySample(linear, tokens)));
  EXPECT_TRUE(torch::equal(time_linear->forward(rows), SampleBySample(time_linear, rows)));
  // The first sample alone, through the same layer: the same bits.
  EXPECT_TRUE(
      torch::equal(conv->forward(images).slice(0, 0, 1), conv->forward(images.slice(0, 0, 1))));
}

TEST_F(BatchInvariantLayersTest, OutsideTheScopeAgreesWithinNoiseAndVectorsPassThrough) {
  torch::InferenceMode inference_mode;
  const torch::Tensor images = torch::randn({3, 32, 8, 8});
  const torch::Tensor tokens = torch::randn({3, 80, 128});
  // Without the scope the batch runs as one call: equal to the
  // sample-by-sample result up to float32 noise (not necessarily bitwise,
  // which is what the scope is for).
  EXPECT_TRUE(torch::allclose(conv->forward(images), SampleBySample(conv, images), 1e-5, 1e-5));
  EXPECT_TRUE(torch::allclose(linear->forward(tokens), SampleBySample(linear, tokens), 1e-5, 1e-5));
  // A 1-D input has no batch dimension; it goes through unchanged.
  BatchInvariantScope scope;
  const torch::Tensor vector = torch::randn({128});
  EXPECT_EQ(linear->forward(vector).sizes(), (std::vector<int64_t>{512}));
}

}  // namespace
}  // namespace fd::model

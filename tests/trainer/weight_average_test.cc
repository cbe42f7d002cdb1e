// trainer/weight_average.h: EMAModel's decay schedule and update, the swap
// that hands the average to the networks and back, and its checkpoint state.
#include "trainer/weight_average.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <map>
#include <string>
#include <vector>

namespace fd::trainer {
namespace {

TEST(WeightAverageTest, DecayFollowsEmaModelsWarmUpUpToTheMaximum) {
  WeightAverage average({torch::zeros({2})}, 0.99);
  EXPECT_EQ(average.DecayAt(1), 0.0);  // the first step's weights, as they are
  EXPECT_DOUBLE_EQ(average.DecayAt(2), 2.0 / 11.0);
  EXPECT_DOUBLE_EQ(average.DecayAt(100), 100.0 / 109.0);
  EXPECT_DOUBLE_EQ(average.DecayAt(100000), 0.99);
}

TEST(WeightAverageTest, UpdatesTowardsTheWeightsAndSwapsWithThem) {
  torch::Tensor w = torch::tensor({0.0F, 10.0F});
  WeightAverage average({w}, 0.5);
  w.copy_(torch::tensor({4.0F, 2.0F}));
  average.Update(1);  // decay 0: the average is the weights
  EXPECT_TRUE(torch::equal(average.average()[0], w));
  w.copy_(torch::tensor({8.0F, 8.0F}));
  average.Update(20);  // decay 0.5
  EXPECT_TRUE(torch::allclose(average.average()[0], torch::tensor({6.0F, 5.0F})));

  average.Swap();
  EXPECT_TRUE(torch::allclose(w, torch::tensor({6.0F, 5.0F})));
  EXPECT_TRUE(torch::equal(average.average()[0], torch::tensor({8.0F, 8.0F})));
  average.Swap();
  EXPECT_TRUE(torch::equal(w, torch::tensor({8.0F, 8.0F})));
}

TEST(WeightAverageTest, StateRoundTripsAndLoadRefusesAnotherStage) {
  torch::Tensor a = torch::arange(6, torch::kFloat32).reshape({2, 3});
  torch::Tensor b = torch::ones({4});
  WeightAverage saved({a, b}, 0.9);
  a.add_(1);
  saved.Update(5);
  const std::map<std::string, torch::Tensor> state = saved.State();
  ASSERT_EQ(state.size(), 2u);

  WeightAverage restored({a.clone(), b.clone()}, 0.9);
  ASSERT_TRUE(restored.Load(state).ok());
  EXPECT_TRUE(torch::equal(restored.average()[0], saved.average()[0]));
  EXPECT_TRUE(torch::equal(restored.average()[1], saved.average()[1]));

  WeightAverage fewer({a.clone()}, 0.9);
  EXPECT_EQ(fewer.Load(state).code(), absl::StatusCode::kInvalidArgument);
  WeightAverage reshaped({a.reshape({3, 2}).clone(), b.clone()}, 0.9);
  const absl::Status refused = reshaped.Load(state);
  EXPECT_EQ(refused.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(refused.message().find("tensor 0"), std::string::npos) << refused;
}

}  // namespace
}  // namespace fd::trainer

// Tests for tests/testing/tensor_matchers.h: the golden acceptance rule and
// the content of the failure messages.
#include "tests/testing/tensor_matchers.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <torch/torch.h>

#include <limits>
#include <string>

namespace fd::testing {
namespace {

using ::testing::AllOf;
using ::testing::HasSubstr;

std::string Message(const ::testing::AssertionResult& result) { return result.message(); }

TEST(TensorMatchersTest, CloseWithinRelativePlusAbsoluteTolerance) {
  const torch::Tensor expected = torch::tensor({1.0f, -4.0f, 2.0f});
  // Tolerance = 1e-4 * 4 + 1e-6 = 4.01e-4.
  EXPECT_TRUE(TensorsClose(expected + torch::tensor({4.0e-4f, 0.0f, 0.0f}), expected));
  EXPECT_FALSE(TensorsClose(expected + torch::tensor({0.0f, 0.0f, 4.2e-4f}), expected));
  EXPECT_TRUE(TensorsClose(expected + 0.05, expected, /*rel=*/0.0125, /*abs=*/0.0));
  // All-zero reference: only the absolute term remains.
  EXPECT_TRUE(TensorsClose(torch::full({2}, 5e-7), torch::zeros({2})));
  EXPECT_FALSE(TensorsClose(torch::full({2}, 2e-6), torch::zeros({2})));
  // Empty tensors of equal shape are close.
  EXPECT_TRUE(TensorsClose(torch::empty({0, 3}), torch::empty({0, 3})));
}

TEST(TensorMatchersTest, FailureMessageReportsWorstElement) {
  torch::Tensor expected = torch::zeros({2, 3, 4});
  expected[0][0][0] = 10.0f;
  torch::Tensor actual = expected.clone();
  actual[1][2][3] = 0.5f;
  const auto result = TensorsClose(actual, expected);
  ASSERT_FALSE(result);
  EXPECT_THAT(Message(result),
              AllOf(HasSubstr("max|a-e| = 0.5"), HasSubstr("[1, 2, 3]"), HasSubstr("max|e| = 10"),
                    HasSubstr("ratio max|a-e|/max|e| = 0.05"), HasSubstr("actual 0.5"),
                    HasSubstr("expected 0"), HasSubstr("1 of 24 elements")));
}

TEST(TensorMatchersTest, ShapeAndDtypeAreCheckedFirst) {
  const auto shape = TensorsClose(torch::zeros({2, 3}), torch::zeros({3, 2}));
  ASSERT_FALSE(shape);
  EXPECT_THAT(Message(shape),
              AllOf(HasSubstr("shape mismatch"), HasSubstr("[2, 3]"), HasSubstr("[3, 2]")));
  const auto dtype = TensorsClose(torch::zeros({2}, torch::kFloat64), torch::zeros({2}));
  ASSERT_FALSE(dtype);
  EXPECT_THAT(Message(dtype), HasSubstr("dtype mismatch"));
  EXPECT_FALSE(TensorsClose(torch::Tensor(), torch::zeros({1})));
  EXPECT_THAT(
      Message(TensorsClose(torch::zeros({1}, torch::kInt64), torch::zeros({1}, torch::kInt64))),
      HasSubstr("TensorsEqual"));
}

TEST(TensorMatchersTest, NonFiniteValues) {
  const float nan = std::numeric_limits<float>::quiet_NaN();
  const float inf = std::numeric_limits<float>::infinity();
  const auto result = TensorsClose(torch::tensor({1.0f, nan}), torch::tensor({1.0f, 2.0f}));
  ASSERT_FALSE(result);
  EXPECT_THAT(Message(result), AllOf(HasSubstr("non-finite"), HasSubstr("[1]")));
  EXPECT_FALSE(TensorsClose(torch::tensor({inf}), torch::tensor({1.0f})));
  EXPECT_TRUE(TensorsClose(torch::tensor({inf, 1.0f}), torch::tensor({inf, 1.0f})));
  EXPECT_TRUE(TensorsClose(torch::tensor({nan, 1.0f}), torch::tensor({nan, 1.0f})));
}

TEST(TensorMatchersTest, ExactEqualityForIntegers) {
  const torch::Tensor expected = torch::tensor({999, 899, 799}, torch::kInt64);
  EXPECT_TRUE(TensorsEqual(expected.clone(), expected));
  const auto result = TensorsEqual(torch::tensor({999, 900, 799}, torch::kInt64), expected);
  ASSERT_FALSE(result);
  EXPECT_THAT(Message(result), AllOf(HasSubstr("1 of 3 elements differ"), HasSubstr("[1]"),
                                     HasSubstr("actual 900"), HasSubstr("expected 899")));
  EXPECT_FALSE(TensorsEqual(expected.to(torch::kInt32), expected));
  EXPECT_TRUE(TensorsEqual(torch::tensor({1, 2}, torch::kUInt8).view({1, 2}),
                           torch::tensor({1, 2}, torch::kUInt8).view({1, 2})));
}

}  // namespace
}  // namespace fd::testing

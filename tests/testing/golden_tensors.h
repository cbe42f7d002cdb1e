// Reading golden tensors and checking results against them, shared by the
// model tests: load a golden file, fetch a tensor by name (a missing one is a
// test failure), and apply the golden acceptance rule while printing the
// achieved error so that test logs document the margins.
#ifndef FD_TESTS_TESTING_GOLDEN_TENSORS_H_
#define FD_TESTS_TESTING_GOLDEN_TENSORS_H_

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <iostream>
#include <map>
#include <string>

#include "model/checkpoint/safetensors.h"
#include "tests/testing/golden.h"
#include "tests/testing/tensor_matchers.h"

namespace fd::testing {

using TensorMap = std::map<std::string, torch::Tensor>;

// Every tensor of GoldenPath(relative); a load error fails the test and
// returns an empty map.
inline TensorMap LoadGoldenTensors(const std::string& relative) {
  auto tensors = fd::model::LoadSafetensors(GoldenPath(relative));
  EXPECT_TRUE(tensors.ok()) << tensors.status();
  return tensors.ok() ? *std::move(tensors) : TensorMap{};
}

// m[key]; a missing key fails the test and returns an undefined tensor.
inline const torch::Tensor& GoldenTensor(const TensorMap& m, const std::string& key) {
  static const torch::Tensor kMissing;
  auto it = m.find(key);
  EXPECT_NE(it, m.end()) << "missing golden tensor " << key;
  return it == m.end() ? kMissing : it->second;
}

// Golden rule: max|actual - expected| <= rel * max|expected| + abs; prints
// the achieved error.
inline void ExpectGoldenClose(const std::string& name, const torch::Tensor& actual,
                              const torch::Tensor& expected, double rel, double abs = 1e-6) {
  EXPECT_TRUE(TensorsClose(actual, expected, rel, abs)) << name;
  if (actual.defined() && expected.defined() && actual.sizes() == expected.sizes()) {
    const double err =
        (actual.to(torch::kFloat64) - expected.to(torch::kFloat64)).abs().max().item<double>();
    const double ref = expected.to(torch::kFloat64).abs().max().item<double>();
    std::cout << "[golden] " << name << " max_abs_err=" << err
              << " rel=" << (ref > 0 ? err / ref : err) << "\n";
  }
}

}  // namespace fd::testing

#endif  // FD_TESTS_TESTING_GOLDEN_TENSORS_H_

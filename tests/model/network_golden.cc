// See network_golden.h.
#include "tests/model/network_golden.h"

#include <torch/torch.h>

#include <algorithm>
#include <cstdio>

#include "model/checkpoint/safetensors.h"
#include "tests/testing/golden.h"
#include "tests/testing/golden_tensors.h"
#include "tests/testing/tensor_matchers.h"

namespace fd::model::testing {
namespace {

std::map<std::string, double>& MaxRel() {
  static auto* values = new std::map<std::string, double>();
  return *values;
}

// Prints the per-file maxima at the end of the run (for the reports), and
// runs LibTorch with 2 threads as the golden generator did.
class NetworkGoldenEnvironment : public ::testing::Environment {
 public:
  void TearDown() override {
    if (MaxRel().empty()) return;
    std::printf("[ golden  ] max relative error per golden file:\n");
    for (const auto& [file, rel] : MaxRel()) {
      std::printf("[ golden  ]   %-28s %.2e\n", file.c_str(), rel);
    }
  }
};
const auto* const kEnvironment = ::testing::AddGlobalTestEnvironment(new NetworkGoldenEnvironment);

}  // namespace

std::map<std::string, torch::Tensor> ReadGolden(const std::string& relative) {
  return fd::testing::LoadGoldenTensors(relative);
}

torch::Tensor GoldenTensor(const std::map<std::string, torch::Tensor>& file,
                           const std::string& key) {
  return fd::testing::GoldenTensor(file, key);
}

::testing::AssertionResult GoldenClose(const std::string& what, const torch::Tensor& actual,
                                       const torch::Tensor& expected) {
  if (!actual.defined() || !expected.defined()) {
    return ::testing::AssertionFailure() << what << ": undefined tensor";
  }
  torch::Tensor a = actual.detach().to(torch::kCPU, expected.scalar_type());
  if (a.sizes() == expected.sizes()) {
    torch::Tensor e = expected.to(torch::kFloat64);
    const double max_ref = e.abs().max().item<double>();
    const double max_diff = (a.to(torch::kFloat64) - e).abs().max().item<double>();
    const std::string file = what.substr(0, what.find(':'));
    double& worst = MaxRel()[file];
    worst = std::max(worst, max_ref > 0 ? max_diff / max_ref : max_diff);
  }
  ::testing::AssertionResult result = fd::testing::TensorsClose(a, expected);
  if (!result) return ::testing::AssertionFailure() << what << ": " << result.message();
  return result;
}

const std::map<std::string, double>& GoldenMaxRelErrors() { return MaxRel(); }

}  // namespace fd::model::testing

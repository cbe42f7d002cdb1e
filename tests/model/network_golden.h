// Helpers for the network golden tests (vae/controlnet/unet/LoRA): reading
// golden files and comparing with the golden acceptance rule of
// ../shared/golden/README.md: max|out - ref| <= 1e-4 * max|ref| + 1e-6.
#ifndef FD_TESTS_MODEL_NETWORK_GOLDEN_H_
#define FD_TESTS_MODEL_NETWORK_GOLDEN_H_

#include <gtest/gtest.h>
#include <torch/types.h>

#include <map>
#include <string>

namespace fd::model::testing {

// All tensors of GoldenPath(relative); an empty map (and a test failure) if
// the file cannot be read.
std::map<std::string, torch::Tensor> ReadGolden(const std::string& relative);

// The tensor `key` of `file`; fails the test (and returns an undefined
// tensor) when absent.
torch::Tensor GoldenTensor(const std::map<std::string, torch::Tensor>& file,
                           const std::string& key);

// Compares `actual` with `expected` under the golden rule (float32; actual
// is converted to float32 on the CPU first). The message names `what` and
// gives max abs and relative error. Also records the relative error for the
// per-file summary printed by PrintGoldenSummary.
::testing::AssertionResult GoldenClose(const std::string& what, const torch::Tensor& actual,
                                       const torch::Tensor& expected);

// Largest relative error (max|out-ref| / max|ref|) recorded per prefix
// (e.g. "A/vae"): `what` is recorded under the part before the first ':'.
const std::map<std::string, double>& GoldenMaxRelErrors();

}  // namespace fd::model::testing

#endif  // FD_TESTS_MODEL_NETWORK_GOLDEN_H_

// GoogleTest assertions for comparing tensors against golden references.
//
//   EXPECT_TRUE(fd::testing::TensorsClose(out, ref));        // floating point
//   EXPECT_TRUE(fd::testing::TensorsEqual(ids, ref_ids));    // integers, exact
//
// TensorsClose implements the golden acceptance rule of
// ../shared/golden/README.md: max|actual - expected| <= rel * max|expected| +
// abs (float32 defaults rel 1e-4, abs 1e-6), after checking that shapes and
// dtypes agree. Failure messages report the max abs difference, max|ref|,
// their ratio, the tolerance and the worst element's index and values.
// Header-only; thread-compatible.
#ifndef FD_TESTS_TESTING_TENSOR_MATCHERS_H_
#define FD_TESTS_TESTING_TENSOR_MATCHERS_H_

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <cstdint>
#include <sstream>
#include <string>
#include <vector>

namespace fd::testing {
namespace tensor_matchers_internal {

inline std::string ShapeString(const torch::Tensor& t) {
  std::ostringstream out;
  out << t.sizes();
  return out.str();
}

// The multi-index of flat (row-major) element `flat` of a tensor of `sizes`.
inline std::string IndexString(int64_t flat, torch::IntArrayRef sizes) {
  std::vector<int64_t> index(sizes.size());
  for (int64_t d = static_cast<int64_t>(sizes.size()) - 1; d >= 0; --d) {
    const int64_t size = sizes[d];
    index[d] = size > 0 ? flat % size : 0;
    flat = size > 0 ? flat / size : 0;
  }
  std::ostringstream out;
  out << "[";
  for (size_t d = 0; d < index.size(); ++d) out << (d ? ", " : "") << index[d];
  out << "]";
  return out.str();
}

// Shared precondition: both defined, same shape, same dtype.
inline ::testing::AssertionResult SameShapeAndDtype(const torch::Tensor& actual,
                                                    const torch::Tensor& expected) {
  if (!actual.defined() || !expected.defined()) {
    return ::testing::AssertionFailure() << "undefined tensor (actual defined: " << actual.defined()
                                         << ", expected defined: " << expected.defined() << ")";
  }
  if (actual.sizes() != expected.sizes()) {
    return ::testing::AssertionFailure() << "shape mismatch: actual " << ShapeString(actual)
                                         << " vs expected " << ShapeString(expected);
  }
  if (actual.scalar_type() != expected.scalar_type()) {
    return ::testing::AssertionFailure()
           << "dtype mismatch: actual " << actual.scalar_type() << " vs expected "
           << expected.scalar_type() << " (shape " << ShapeString(actual) << ")";
  }
  return ::testing::AssertionSuccess();
}

}  // namespace tensor_matchers_internal

// max|actual - expected| <= rel * max|expected| + abs, elementwise in float64
// on the CPU. Non-finite values fail unless both tensors hold the identical
// non-finite value at that position.
inline ::testing::AssertionResult TensorsClose(const torch::Tensor& actual,
                                               const torch::Tensor& expected, double rel = 1e-4,
                                               double abs = 1e-6) {
  namespace internal = tensor_matchers_internal;
  ::testing::AssertionResult same = internal::SameShapeAndDtype(actual, expected);
  if (!same) return same;
  if (!actual.is_floating_point() && !actual.is_complex()) {
    return ::testing::AssertionFailure()
           << "TensorsClose on " << actual.scalar_type() << " tensors: use TensorsEqual";
  }
  if (expected.numel() == 0) return ::testing::AssertionSuccess();

  const torch::Tensor a = actual.detach().to(torch::kCPU, torch::kFloat64).contiguous().flatten();
  const torch::Tensor e = expected.detach().to(torch::kCPU, torch::kFloat64).contiguous().flatten();
  // Identical infinities (and NaN vs NaN) count as equal; other non-finite
  // differences are failures.
  const torch::Tensor both_nan = torch::isnan(a) & torch::isnan(e);
  const torch::Tensor same_value = (a == e) | both_nan;
  torch::Tensor diff = (a - e).abs();
  diff = torch::where(same_value, torch::zeros_like(diff), diff);
  const torch::Tensor bad = ~torch::isfinite(diff);
  if (bad.any().item<bool>()) {
    const int64_t first = bad.nonzero()[0][0].item<int64_t>();
    return ::testing::AssertionFailure()
           << bad.sum().item<int64_t>() << " non-finite difference(s) in a tensor of shape "
           << internal::ShapeString(actual) << "; first at "
           << internal::IndexString(first, actual.sizes()) << ": actual " << a[first].item<double>()
           << ", expected " << e[first].item<double>();
  }
  const torch::Tensor finite_ref = torch::where(torch::isfinite(e), e.abs(), torch::zeros_like(e));
  const double max_ref = finite_ref.max().item<double>();
  const int64_t worst = diff.argmax().item<int64_t>();
  const double max_diff = diff[worst].item<double>();
  const double tolerance = rel * max_ref + abs;
  std::ostringstream report;
  report.precision(6);
  report << "shape " << internal::ShapeString(actual) << ": max|a-e| = " << max_diff << " at "
         << internal::IndexString(worst, actual.sizes()) << " (actual " << a[worst].item<double>()
         << ", expected " << e[worst].item<double>() << "), max|e| = " << max_ref
         << ", ratio max|a-e|/max|e| = " << (max_ref > 0 ? max_diff / max_ref : max_diff)
         << ", tolerance " << rel << " * max|e| + " << abs << " = " << tolerance;
  if (max_diff <= tolerance) return ::testing::AssertionSuccess() << report.str();
  return ::testing::AssertionFailure()
         << "tensors differ: " << report.str() << ", " << (diff > tolerance).sum().item<int64_t>()
         << " of " << diff.numel() << " elements out of tolerance";
}

// Exact equality (integer, bool or any dtype): same shape, dtype and values.
inline ::testing::AssertionResult TensorsEqual(const torch::Tensor& actual,
                                               const torch::Tensor& expected) {
  namespace internal = tensor_matchers_internal;
  ::testing::AssertionResult same = internal::SameShapeAndDtype(actual, expected);
  if (!same) return same;
  const torch::Tensor a = actual.detach().to(torch::kCPU).contiguous().flatten();
  const torch::Tensor e = expected.detach().to(torch::kCPU).contiguous().flatten();
  if (torch::equal(a, e)) return ::testing::AssertionSuccess();
  const torch::Tensor mismatch = a.ne(e);
  const int64_t first = mismatch.nonzero()[0][0].item<int64_t>();
  std::ostringstream values;
  values << "actual " << a[first].item() << ", expected " << e[first].item();
  return ::testing::AssertionFailure()
         << mismatch.sum().item<int64_t>() << " of " << a.numel()
         << " elements differ in a tensor of shape " << internal::ShapeString(actual)
         << "; first at " << internal::IndexString(first, actual.sizes()) << ": " << values.str();
}

}  // namespace fd::testing

#endif  // FD_TESTS_TESTING_TENSOR_MATCHERS_H_

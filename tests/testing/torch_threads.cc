// Linked into every test binary that runs LibTorch: Debian's LibTorch uses one
// thread by default, while the goldens' tolerances were measured with 2.
// gtest runs global environments in every process, so each ctest-discovered
// test gets the setting too.
#include <ATen/Parallel.h>
#include <gtest/gtest.h>

namespace {

class TorchThreadsEnvironment : public ::testing::Environment {
 public:
  void SetUp() override { at::set_num_threads(2); }
};

const auto* const kTorchThreads =
    ::testing::AddGlobalTestEnvironment(new TorchThreadsEnvironment);

}  // namespace

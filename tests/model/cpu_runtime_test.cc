// Tests model/cpu_runtime: the process-wide CPU settings the server and the
// benchmarks apply at start-up.
#include "model/runtime/cpu_runtime.h"

#include <dlfcn.h>
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <cstdlib>
#include <optional>
#include <string>

namespace fd::model {
namespace {

using ::testing::HasSubstr;

// Sets (or unsets, with nullopt) an environment variable for one scope.
class ScopedEnv {
 public:
  ScopedEnv(const char* name, std::optional<std::string> value) : name_(name) {
    if (const char* old = std::getenv(name)) old_ = old;
    if (value) {
      setenv(name, value->c_str(), 1);
    } else {
      unsetenv(name);
    }
  }
  ~ScopedEnv() {
    if (old_) {
      setenv(name_, old_->c_str(), 1);
    } else {
      unsetenv(name_);
    }
  }

 private:
  const char* name_;
  std::optional<std::string> old_;
};

struct OpenBlas {
  void (*set_threads)(int);
  int (*get_threads)();
};

// The project installs OpenBLAS (scripts/setup-deps.sh); LibTorch reaches it
// through libblas.so.3. A machine with the reference BLAS fails here.
OpenBlas FindOpenBlas() {
  return {reinterpret_cast<void (*)(int)>(dlsym(RTLD_DEFAULT, "openblas_set_num_threads")),
          reinterpret_cast<int (*)()>(dlsym(RTLD_DEFAULT, "openblas_get_num_threads"))};
}

TEST(UseSingleThreadedBlasTest, PutsOpenBlasOnTheCallingThread) {
  const OpenBlas blas = FindOpenBlas();
  ASSERT_NE(blas.set_threads, nullptr) << "LibTorch's BLAS is not OpenBLAS";
  ASSERT_NE(blas.get_threads, nullptr);
  ScopedEnv openblas("OPENBLAS_NUM_THREADS", std::nullopt);
  ScopedEnv goto_threads("GOTO_NUM_THREADS", std::nullopt);
  blas.set_threads(2);
  const int before = blas.get_threads();

  const std::string description = UseSingleThreadedBlas();

  EXPECT_EQ(blas.get_threads(), 1);
  EXPECT_EQ(description, "blas: OpenBLAS threads " + std::to_string(before) + " -> 1");
}

TEST(UseSingleThreadedBlasTest, RespectsAnExplicitThreadCount) {
  const OpenBlas blas = FindOpenBlas();
  ASSERT_NE(blas.set_threads, nullptr) << "LibTorch's BLAS is not OpenBLAS";
  ScopedEnv openblas("OPENBLAS_NUM_THREADS", "2");
  blas.set_threads(2);
  const int before = blas.get_threads();

  const std::string description = UseSingleThreadedBlas();

  EXPECT_EQ(blas.get_threads(), before);
  EXPECT_THAT(description, HasSubstr("OPENBLAS_NUM_THREADS"));
  blas.set_threads(1);
}

TEST(BoundedOpenMpSpinTest, AddsPassiveWithABoundedSpinUnlessTheUserSetEither) {
  {
    ScopedEnv policy("OMP_WAIT_POLICY", std::nullopt);
    ScopedEnv spin("GOMP_SPINCOUNT", std::nullopt);
    const auto settings = BoundedOpenMpSpinSettings();
    ASSERT_EQ(settings.size(), 2u);
    EXPECT_EQ(settings[0], std::make_pair(std::string("OMP_WAIT_POLICY"), std::string("PASSIVE")));
    EXPECT_EQ(settings[1],
              std::make_pair(std::string("GOMP_SPINCOUNT"), std::string(kOpenMpSpinCount)));
    EXPECT_EQ(DescribeOpenMpWaiting(), "");
  }
  {
    ScopedEnv policy("OMP_WAIT_POLICY", "ACTIVE");
    ScopedEnv spin("GOMP_SPINCOUNT", std::nullopt);
    EXPECT_TRUE(BoundedOpenMpSpinSettings().empty());
    EXPECT_EQ(DescribeOpenMpWaiting(), "OMP_WAIT_POLICY=ACTIVE");
  }
  {
    ScopedEnv policy("OMP_WAIT_POLICY", std::nullopt);
    ScopedEnv spin("GOMP_SPINCOUNT", "1000");
    EXPECT_TRUE(BoundedOpenMpSpinSettings().empty());
    EXPECT_EQ(DescribeOpenMpWaiting(), "GOMP_SPINCOUNT=1000");
  }
}

TEST(TuneMallocForInferenceTest, TunesGlibcUnlessTheEnvironmentDoes) {
  {
    ScopedEnv tunables("GLIBC_TUNABLES", "glibc.malloc.check=0");
    EXPECT_EQ(TuneMallocForInference(), "malloc: left as the environment sets it");
  }
  ScopedEnv tunables("GLIBC_TUNABLES", std::nullopt);
  ScopedEnv mmap("MALLOC_MMAP_THRESHOLD_", std::nullopt);
  ScopedEnv trim("MALLOC_TRIM_THRESHOLD_", std::nullopt);
  EXPECT_EQ(TuneMallocForInference(), "malloc: mmap threshold 32 MiB, heap trimming off");
}

}  // namespace
}  // namespace fd::model

// Where the benchmarks find the golden checkpoints they run on: the
// benchmarked models are the goldens' (config B, the tiny pipeline, CLIP).
// $FD_GOLDEN_DIR when set, else the build-time default (../shared/golden
// beside the checkout). The benchmarks read the folder like any user would;
// they do not use the tests' helpers (tests/layering_test.sh).
#ifndef FD_BENCH_GOLDEN_DATA_H_
#define FD_BENCH_GOLDEN_DATA_H_

#include <cstdlib>
#include <string>

namespace fd::bench {

// The golden folder + "/" + `relative`. Thread-safety: reads the environment.
inline std::string BenchGoldenPath(const std::string& relative) {
  const char* env = std::getenv("FD_GOLDEN_DIR");
#ifdef FD_DEFAULT_GOLDEN_DIR
  const std::string dir = env != nullptr && *env != '\0' ? env : FD_DEFAULT_GOLDEN_DIR;
#else
  const std::string dir = env != nullptr && *env != '\0' ? env : "../shared/golden";
#endif
  return dir + "/" + relative;
}

}  // namespace fd::bench

#endif  // FD_BENCH_GOLDEN_DATA_H_

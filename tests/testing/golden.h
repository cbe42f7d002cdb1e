// Locating and reading the golden reference vectors in tests.
//
// The golden directory is $FD_GOLDEN_DIR when set, else the build-time
// default (../shared/golden beside the checkout). Tests must read shapes,
// batch sizes and seeds from the files, never assume them.
#ifndef FD_TESTS_TESTING_GOLDEN_H_
#define FD_TESTS_TESTING_GOLDEN_H_

#include <cstdlib>
#include <string>

namespace fd::testing {

inline std::string GoldenDir() {
  if (const char* env = std::getenv("FD_GOLDEN_DIR"); env != nullptr && *env != '\0') {
    return env;
  }
#ifdef FD_DEFAULT_GOLDEN_DIR
  return FD_DEFAULT_GOLDEN_DIR;
#else
  return "../shared/golden";
#endif
}

// GoldenDir() + "/" + relative.
inline std::string GoldenPath(const std::string& relative) { return GoldenDir() + "/" + relative; }

}  // namespace fd::testing

#endif  // FD_TESTS_TESTING_GOLDEN_H_

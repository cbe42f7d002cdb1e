#include "model/runtime/cpu_runtime.h"

#include <dlfcn.h>
#include <unistd.h>

#include <cstdlib>

#if defined(__GLIBC__)
#include <malloc.h>
#endif

namespace fd::model {

std::string TuneMallocForInference() {
#if defined(__GLIBC__)
  if (std::getenv("MALLOC_MMAP_THRESHOLD_") != nullptr ||
      std::getenv("MALLOC_TRIM_THRESHOLD_") != nullptr ||
      std::getenv("GLIBC_TUNABLES") != nullptr) {
    return "malloc: left as the environment sets it";
  }
  // glibc caps the mmap threshold at HEAP_MAX_SIZE / 2 (32 MiB on 64-bit).
  constexpr int kMmapThreshold = 32 * 1024 * 1024;
  // Setting either value also turns off glibc's dynamic threshold.
  const bool mmap_ok = mallopt(M_MMAP_THRESHOLD, kMmapThreshold) == 1;
  const bool trim_ok = mallopt(M_TRIM_THRESHOLD, -1) == 1;  // -1: never trim (as size_t max)
  if (mmap_ok && trim_ok) return "malloc: mmap threshold 32 MiB, heap trimming off";
  return "malloc: tuning refused by the C library";
#else
  return "malloc: not glibc, left alone";
#endif
}

std::vector<std::pair<std::string, std::string>> BoundedOpenMpSpinSettings() {
  if (std::getenv("OMP_WAIT_POLICY") != nullptr || std::getenv("GOMP_SPINCOUNT") != nullptr) {
    return {};
  }
  return {{"OMP_WAIT_POLICY", "PASSIVE"}, {"GOMP_SPINCOUNT", kOpenMpSpinCount}};
}

void UseBoundedOpenMpSpin(char** argv) {
  const std::vector<std::pair<std::string, std::string>> settings = BoundedOpenMpSpinSettings();
  if (settings.empty()) return;
  for (const auto& [name, value] : settings) setenv(name.c_str(), value.c_str(), /*overwrite=*/1);
  execv("/proc/self/exe", argv);
  // exec failed (no /proc): run on with libgomp's defaults.
}

std::string DescribeOpenMpWaiting() {
  std::string out;
  for (const char* name : {"OMP_WAIT_POLICY", "GOMP_SPINCOUNT"}) {
    if (const char* value = std::getenv(name)) {
      if (!out.empty()) out += " ";
      out += std::string(name) + "=" + value;
    }
  }
  return out;
}

std::string UseSingleThreadedBlas() {
  for (const char* variable : {"OPENBLAS_NUM_THREADS", "GOTO_NUM_THREADS"}) {
    if (std::getenv(variable) != nullptr) {
      return std::string("blas: threads left as ") + variable + " sets them";
    }
  }
  using SetThreads = void (*)(int);
  using GetThreads = int (*)();
  auto set_threads = reinterpret_cast<SetThreads>(dlsym(RTLD_DEFAULT, "openblas_set_num_threads"));
  auto get_threads = reinterpret_cast<GetThreads>(dlsym(RTLD_DEFAULT, "openblas_get_num_threads"));
  if (set_threads == nullptr || get_threads == nullptr) return "blas: not OpenBLAS, left alone";
  const int before = get_threads();
  set_threads(1);
  return "blas: OpenBLAS threads " + std::to_string(before) + " -> " +
         std::to_string(get_threads());
}

}  // namespace fd::model

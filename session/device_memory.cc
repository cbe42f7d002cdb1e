#include "session/device_memory.h"

#include <torch/types.h>
#include <unistd.h>

#include <exception>
#include <fstream>
#include <string>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"

#ifdef FD_WITH_CUDA
#include <c10/cuda/CUDACachingAllocator.h>
#include <c10/cuda/CUDAFunctions.h>
#endif

namespace fd::session {
namespace {

// /proc/self/statm: "size resident shared text lib data dt", in pages.
absl::StatusOr<int64_t> ResidentSetBytes() {
  constexpr char kPath[] = "/proc/self/statm";
  std::ifstream statm(kPath);
  if (!statm) return absl::UnavailableError(absl::StrCat(kPath, ": cannot be opened"));
  int64_t size_pages = 0;
  int64_t resident_pages = 0;
  if (!(statm >> size_pages >> resident_pages) || resident_pages < 0) {
    return absl::UnavailableError(
        absl::StrCat(kPath, ": expected \"<size> <resident> ...\" in pages, could not parse it"));
  }
  const long page_size = sysconf(_SC_PAGESIZE);
  if (page_size <= 0) return absl::UnavailableError("sysconf(_SC_PAGESIZE) failed");
  return resident_pages * static_cast<int64_t>(page_size);
}

#ifdef FD_WITH_CUDA
// Runs on the metrics (scrape) thread: an exception from the CUDA runtime
// (a lost device, a bad index) would end the process there, so it becomes
// UNAVAILABLE and the gauge keeps its last value.
absl::StatusOr<int64_t> CudaAllocatedBytes(const torch::Device& device) {
  try {
    const int index = device.has_index() ? device.index() : c10::cuda::current_device();
    const auto stats = c10::cuda::CUDACachingAllocator::getDeviceStats(index);
    // Index 0 is StatType::AGGREGATE (all pools) in every LibTorch version;
    // the enum itself moved namespaces between versions.
    return static_cast<int64_t>(stats.allocated_bytes[0].current);
  } catch (const std::exception& e) {
    return absl::UnavailableError(
        absl::StrCat("device ", device.str(), ": CUDA memory stats failed: ", e.what()));
  }
}
#endif

}  // namespace

absl::StatusOr<int64_t> DeviceMemoryInUseBytes(const std::string& name) {
  torch::Device device = torch::kCPU;
  try {
    device = torch::Device(name);
  } catch (const std::exception& e) {
    return absl::InvalidArgumentError(absl::StrCat("device '", name, "': not a device name"));
  }
  if (device.is_cpu()) return ResidentSetBytes();
#ifdef FD_WITH_CUDA
  if (device.is_cuda()) return CudaAllocatedBytes(device);
#endif
  return absl::UnimplementedError(absl::StrCat("device ", device.str(),
                                               ": memory in use is measured only for cpu",
#ifdef FD_WITH_CUDA
                                               " and cuda"
#else
                                               " (cuda needs a build with FD_WITH_CUDA)"
#endif
                                               ));
}

}  // namespace fd::session

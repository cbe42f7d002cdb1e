#include "session/compute_runtime.h"

#include <ATen/Parallel.h>
#include <torch/types.h>
#include <torch/version.h>

#include <exception>

#include "absl/strings/str_cat.h"
#include "model/runtime/cpu_runtime.h"

namespace fd::session {

absl::StatusOr<EnvironmentLoadOptions> ParseLoadOptions(const std::string& device,
                                                        const std::string& dtype) {
  EnvironmentLoadOptions options;
  try {
    options.device = torch::Device(device);
  } catch (const std::exception& e) {
    return absl::InvalidArgumentError(absl::StrCat("--device: invalid device '", device, "'"));
  }
  if (dtype == "float32") {
    options.dtype = torch::kFloat32;
  } else if (dtype == "float16") {
    options.dtype = torch::kFloat16;
  } else if (dtype == "bfloat16") {
    options.dtype = torch::kBFloat16;
  } else {
    return absl::InvalidArgumentError(
        absl::StrCat("--dtype: expected float32, float16 or bfloat16, got '", dtype, "'"));
  }
  return options;
}

std::string DeviceName(const EnvironmentLoadOptions& options) { return options.device.str(); }

bool IsCpuDevice(const EnvironmentLoadOptions& options) { return options.device.is_cpu(); }

std::string TorchVersion() { return TORCH_VERSION; }

void UsePassiveOpenMpWaitPolicy(char** argv) { model::UsePassiveOpenMpWaitPolicy(argv); }

std::string TuneMallocForInference() { return model::TuneMallocForInference(); }

std::string UseSingleThreadedBlas() { return model::UseSingleThreadedBlas(); }

void SetIntraOpThreads(int threads) { at::set_num_threads(threads); }

}  // namespace fd::session

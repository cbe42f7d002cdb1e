#include "session/compute_runtime.h"

#include <ATen/Parallel.h>
#include <torch/types.h>
#include <torch/version.h>

#include <algorithm>
#include <exception>

#include "absl/strings/str_cat.h"
#include "model/runtime/attention_kernel.h"
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

void UseBoundedOpenMpSpin(char** argv) { model::UseBoundedOpenMpSpin(argv); }

std::string DescribeOpenMpWaiting() { return model::DescribeOpenMpWaiting(); }

WorkerThreads ResolveWorkerThreads(const WorkerThreadsRequest& r) {
  const int cores = std::max(1, r.cores);
  WorkerThreads out;
  if (!r.cpu) {
    // One worker feeds a GPU; its host-side threads as asked or the cores.
    out.workers = r.workers > 0 ? r.workers : 1;
    out.threads_per_worker = r.threads > 0 ? r.threads : std::max(1, cores / out.workers);
    return out;
  }
  const int batch_cap = std::max(1, r.max_batch_size);
  if (r.workers > 0) {
    out.workers = r.workers;
  } else if (r.threads > 0) {
    // Asked for threads: as many workers as leave every thread a core.
    out.workers = std::clamp(cores / r.threads, 1, batch_cap);
  } else {
    out.workers = std::min(cores, batch_cap);
  }
  out.threads_per_worker = r.threads > 0 ? r.threads : std::max(1, cores / out.workers);
  out.oversubscribed = out.workers * out.threads_per_worker > cores;
  return out;
}

std::string TuneMallocForInference() { return model::TuneMallocForInference(); }

std::string UseSingleThreadedBlas() { return model::UseSingleThreadedBlas(); }

std::string DescribeFusedAttention() { return model::DescribeFusedAttention(); }

void SetIntraOpThreads(int threads) { at::set_num_threads(threads); }

}  // namespace fd::session

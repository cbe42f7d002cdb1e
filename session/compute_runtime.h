// What the server configures on the model runtime, named with plain strings
// and numbers, so that server/ needs no LibTorch and no model/ header: the
// device and dtype environments load with, the process-wide CPU settings for
// inference (model/runtime/cpu_runtime.h), the intra-op thread count and
// the LibTorch version for the build-info metric.
#ifndef FD_SESSION_COMPUTE_RUNTIME_H_
#define FD_SESSION_COMPUTE_RUNTIME_H_

#include <string>

#include "absl/status/statusor.h"
#include "model/pipeline/environment.h"

namespace fd::session {

// The options environments are loaded with (device, dtype, LoRA policy...).
// The layers above pass it through without looking inside.
using EnvironmentLoadOptions = model::EnvironmentOptions;
// A loaded environment's model; opaque to the layers above.
using EnvironmentModel = model::Environment;

// --device ("cpu", "cuda", "cuda:1") and --dtype ("float32", "float16",
// "bfloat16") as load options. INVALID_ARGUMENT naming the flag:
// "--device: invalid device 'x'", "--dtype: expected float32, float16 or
// bfloat16, got 'x'". Thread-safety: pure function.
absl::StatusOr<EnvironmentLoadOptions> ParseLoadOptions(const std::string& device,
                                                        const std::string& dtype);

// The device of `options` as a name ("cpu", "cuda:0"), and whether it is
// the CPU.
std::string DeviceName(const EnvironmentLoadOptions& options);
bool IsCpuDevice(const EnvironmentLoadOptions& options);

// The LibTorch version string (e.g. "1.13.1").
std::string TorchVersion();

// Process-wide settings for a serving process, for main() (see
// model/runtime/cpu_runtime.h; each returns what it did, for the log).
// Call UseBoundedOpenMpSpin first: it may re-execute the process.
void UseBoundedOpenMpSpin(char** argv);
std::string DescribeOpenMpWaiting();
std::string TuneMallocForInference();
std::string UseSingleThreadedBlas();
// Which fused CPU attention kernel the networks use ("avx512", "avx2" or
// "off: <why>"; model/runtime/attention_kernel.h).
std::string DescribeFusedAttention();
// How many batcher workers an environment runs and how many intra-op
// threads each (docs/BENCHMARKS.md, "Threading policy"). On a CPU, with
// both flags 0 (auto): one single-threaded worker per core, at most one per
// frame of a full batch (frames of different sessions split across cores
// better than one frame's small kernels). A thread count given alone gets
// cores / threads workers (at least 1), so that --threads 2 on 2 cores is
// 1 worker x 2 threads, whose OpenMP threads may spin (UseBoundedOpenMpSpin),
// not 2 x 2, where libgomp stops spinning and each frame is slower. Given
// explicitly, both are kept; `oversubscribed` then says whether workers x
// threads exceeds the cores (the server logs a warning). On a GPU: 1 worker.
// Thread-safety: pure function.
struct WorkerThreadsRequest {
  int cores = 1;
  bool cpu = true;
  int max_batch_size = 1;
  int workers = 0;  // --scheduler_workers; 0 = auto
  int threads = 0;  // --threads; 0 = auto
};
struct WorkerThreads {
  int workers = 1;
  int threads_per_worker = 1;
  bool oversubscribed = false;
};
WorkerThreads ResolveWorkerThreads(const WorkerThreadsRequest& request);

// LibTorch intra-op threads of the calling thread (and the default for
// threads started later): torch::set_num_threads.
void SetIntraOpThreads(int threads);

}  // namespace fd::session

#endif  // FD_SESSION_COMPUTE_RUNTIME_H_

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
// Call UsePassiveOpenMpWaitPolicy first: it may re-execute the process.
void UsePassiveOpenMpWaitPolicy(char** argv);
std::string TuneMallocForInference();
std::string UseSingleThreadedBlas();
// LibTorch intra-op threads of the calling thread (and the default for
// threads started later): torch::set_num_threads.
void SetIntraOpThreads(int threads);

}  // namespace fd::session

#endif  // FD_SESSION_COMPUTE_RUNTIME_H_

// How much memory a torch device is using right now, for the device-memory
// gauge (server/metrics.h). Kept apart from metrics so that the CUDA-only
// code path is one small file.
#ifndef FD_SERVER_DEVICE_MEMORY_H_
#define FD_SERVER_DEVICE_MEMORY_H_

#include <torch/types.h>

#include <cstdint>

#include "absl/status/statusor.h"

namespace fd::server {

// Bytes in use on `device`:
//  * CPU: the process's resident set size (/proc/self/statm), because CPU
//    tensors live in ordinary process memory next to everything else.
//  * CUDA (only when compiled with FD_WITH_CUDA, which a CUDA build defines):
//    the bytes torch's CUDA caching allocator has handed out ("allocated"),
//    not the larger reserved pool, on `device`'s index (the current device
//    when it has none).
// Errors: UNIMPLEMENTED naming the device for any other device type (and for
// CUDA in a build without FD_WITH_CUDA); UNAVAILABLE when /proc/self/statm
// cannot be read or parsed.
// Thread-safety: safe to call from any thread.
absl::StatusOr<int64_t> DeviceMemoryInUseBytes(const torch::Device& device);

}  // namespace fd::server

#endif  // FD_SERVER_DEVICE_MEMORY_H_

// How much memory a compute device is using right now, for the server's
// device-memory gauge (server/metrics.h). The device is named as on the
// command line ("cpu", "cuda", "cuda:1"), so the server needs no LibTorch.
// Kept apart so that the CUDA-only code path is one small file.
#ifndef FD_SESSION_DEVICE_MEMORY_H_
#define FD_SESSION_DEVICE_MEMORY_H_

#include <cstdint>
#include <string>

#include "absl/status/statusor.h"

namespace fd::session {

// Bytes in use on `device`:
//  * CPU: the process's resident set size (/proc/self/statm), because CPU
//    tensors live in ordinary process memory next to everything else.
//  * CUDA (only when compiled with FD_WITH_CUDA, which a CUDA build defines):
//    the bytes torch's CUDA caching allocator has handed out ("allocated"),
//    not the larger reserved pool, on `device`'s index (the current device
//    when it has none).
// Errors: INVALID_ARGUMENT for a device name LibTorch does not parse;
// UNIMPLEMENTED naming the device for any other device type (and for CUDA in
// a build without FD_WITH_CUDA); UNAVAILABLE when /proc/self/statm cannot be
// read or parsed, or the CUDA runtime fails (never throws: the metrics
// thread calls it).
// Thread-safety: safe to call from any thread.
absl::StatusOr<int64_t> DeviceMemoryInUseBytes(const std::string& device);

}  // namespace fd::session

#endif  // FD_SESSION_DEVICE_MEMORY_H_

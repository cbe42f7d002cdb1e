// The boundary guard that turns LibTorch exceptions into statuses.
//
// No exception may leave fd::model: every public entry point that calls
// LibTorch wraps the call in TorchCall so that a c10::Error or
// std::exception becomes absl::InternalError.
#ifndef FD_MODEL_RUNTIME_TORCH_CALL_H_
#define FD_MODEL_RUNTIME_TORCH_CALL_H_

#include <exception>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace fd::model {

// Runs `fn` (returning absl::Status or absl::StatusOr<T>) and converts any
// exception it throws into absl::InternalError("<context>: <what>").
template <typename Fn>
auto TorchCall(const char* context, Fn&& fn) -> decltype(fn()) {
  try {
    return fn();
  } catch (const std::exception& e) {
    return absl::InternalError(std::string(context) + ": " + e.what());
  } catch (...) {
    return absl::InternalError(std::string(context) + ": unknown exception");
  }
}

}  // namespace fd::model

#endif  // FD_MODEL_RUNTIME_TORCH_CALL_H_

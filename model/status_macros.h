// Status propagation helpers for code that returns absl::Status/StatusOr,
// and the boundary guard that turns LibTorch exceptions into statuses.
//
// No exception may leave fd::model: every public entry point that calls
// LibTorch wraps the call in FD_TORCH_GUARD (or TorchCall) so that a c10::Error
// or std::exception becomes absl::InternalError / InvalidArgumentError.
#ifndef FD_MODEL_STATUS_MACROS_H_
#define FD_MODEL_STATUS_MACROS_H_

#include <exception>
#include <string>
#include <type_traits>
#include <utility>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

// Returns from the enclosing function if `expr` (an absl::Status) is not OK.
#define FD_RETURN_IF_ERROR(expr)                  \
  do {                                            \
    ::absl::Status fd_status_macro_ = (expr);     \
    if (!fd_status_macro_.ok()) return fd_status_macro_; \
  } while (false)

#define FD_STATUS_CONCAT_INNER_(a, b) a##b
#define FD_STATUS_CONCAT_(a, b) FD_STATUS_CONCAT_INNER_(a, b)

// `lhs = value of expr` (an absl::StatusOr<T>), or returns its error.
// lhs may declare a variable: FD_ASSIGN_OR_RETURN(auto x, MakeX());
#define FD_ASSIGN_OR_RETURN(lhs, expr) \
  FD_ASSIGN_OR_RETURN_IMPL_(FD_STATUS_CONCAT_(fd_statusor_, __LINE__), lhs, expr)
#define FD_ASSIGN_OR_RETURN_IMPL_(tmp, lhs, expr) \
  auto tmp = (expr);                              \
  if (!tmp.ok()) return std::move(tmp).status();  \
  lhs = std::move(tmp).value()

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

#endif  // FD_MODEL_STATUS_MACROS_H_

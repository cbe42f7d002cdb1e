// Status propagation helpers for code that returns absl::Status/StatusOr.
// Used by every component (fd::base has no dependencies but abseil).
#ifndef FD_BASE_STATUS_MACROS_H_
#define FD_BASE_STATUS_MACROS_H_

#include <utility>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

// Returns from the enclosing function if `expr` (an absl::Status) is not OK.
#define FD_RETURN_IF_ERROR(expr)                         \
  do {                                                   \
    ::absl::Status fd_status_macro_ = (expr);            \
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

#endif  // FD_BASE_STATUS_MACROS_H_

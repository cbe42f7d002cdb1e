#include "session/session_metrics.h"

namespace fd::session {

std::string_view RejectReasonName(RejectReason reason) {
  switch (reason) {
    case RejectReason::kTotalLimit:
      return "total_limit";
    case RejectReason::kEnvironmentLimit:
      return "environment_limit";
    case RejectReason::kClientLimit:
      return "client_limit";
    case RejectReason::kPermissionDenied:
      return "permission_denied";
    case RejectReason::kDraining:
      return "draining";
  }
  return "unknown";
}

}  // namespace fd::session

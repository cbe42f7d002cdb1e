#include "session/end_reason.h"

#include <string>

#include "absl/strings/cord.h"
#include "absl/strings/str_cat.h"
#include "session/string_view_compat.h"

namespace fd::session {
namespace {

constexpr std::string_view kEndReasonPayloadUrl = "type.framediffuser.io/fd.session.EndReason";

std::string_view Explanation(EndReason reason) {
  switch (reason) {
    case EndReason::kDraining:
      return "draining (the server is shutting down; open a new session elsewhere)";
    case EndReason::kEvicted:
      return "evicted by the server";
    case EndReason::kExpired:
      return "expired (it was idle for longer than the server's idle timeout)";
    case EndReason::kClosed:
      return "closed by its client";
  }
  return "ended";
}

}  // namespace

std::string_view EndReasonName(EndReason reason) {
  switch (reason) {
    case EndReason::kDraining:
      return "draining";
    case EndReason::kEvicted:
      return "evicted";
    case EndReason::kExpired:
      return "expired";
    case EndReason::kClosed:
      return "closed";
  }
  return "unknown";
}

absl::Status SessionEndedError(std::string_view session_id, EndReason reason,
                               std::string_view detail) {
  absl::Status status = absl::NotFoundError(
      absl::StrCat("session ", ToAbsl(session_id), " has ended: ", ToAbsl(Explanation(reason)),
                   detail.empty() ? "" : ": ", ToAbsl(detail)));
  status.SetPayload(ToAbsl(kEndReasonPayloadUrl), absl::Cord(ToAbsl(EndReasonName(reason))));
  return status;
}

std::optional<EndReason> EndReasonFromStatus(const absl::Status& status) {
  auto payload = status.GetPayload(ToAbsl(kEndReasonPayloadUrl));
  if (!payload.has_value()) return std::nullopt;
  const std::string name(*payload);
  for (EndReason reason :
       {EndReason::kDraining, EndReason::kEvicted, EndReason::kExpired, EndReason::kClosed}) {
    if (name == EndReasonName(reason)) return reason;
  }
  return std::nullopt;
}

}  // namespace fd::session

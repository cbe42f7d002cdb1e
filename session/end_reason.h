// Why a session ended, as the store remembers it and reports it to a client
// that tries to resume (the wire API's SessionNotice.Reason).
#ifndef FD_SESSION_END_REASON_H_
#define FD_SESSION_END_REASON_H_

#include <cstdint>
#include <optional>
#include <string_view>

#include "absl/status/status.h"

namespace fd::session {

// Values equal framediffuser.v1.SessionNotice.Reason's.
enum class EndReason : uint8_t {
  kDraining = 1,  // the server is shutting down (SessionStore::DrainAll)
  kEvicted = 2,   // the server evicted it (SessionStore::Evict*)
  kExpired = 3,   // it idled out (SessionStore::ExpireIdle)
  kClosed = 4,    // its client closed it (SessionStore::Close)
};

// "draining", "evicted", "expired", "closed".
std::string_view EndReasonName(EndReason reason);

// NOT_FOUND "session <id> has ended: <explanation>[: <detail>]", carrying the
// reason as a status payload so that EndReasonFromStatus() recovers it
// without a second (racy) store lookup.
absl::Status SessionEndedError(std::string_view session_id, EndReason reason,
                               std::string_view detail);

// The reason a SessionEndedError carries; nullopt for any other status.
std::optional<EndReason> EndReasonFromStatus(const absl::Status& status);

}  // namespace fd::session

#endif  // FD_SESSION_END_REASON_H_

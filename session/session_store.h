// The server's live sessions: create, look up, resume, close; limits; idle
// expiry; and a bounded memory of sessions that ended and why, so a client
// that comes back is told "expired" or "evicted" rather than "unknown
// session" (silent eviction is what users of other servers complain about).
//
// Secrets. A session id (public: it is sent as metadata for load-balancer
// stickiness) and a separate resume secret are each 128 bits from the OS
// CSPRNG (random_token.h), 32 lowercase hex characters. The store keeps the
// secret itself, in this process's memory only: it is never logged, never
// part of an exported state blob and never returned after Create. Hashing it
// would only help against someone who can read this process's memory, who
// could then take the sessions' frames anyway. Secrets are compared in
// constant time.
//
// Ended sessions are remembered (id, reason, detail, owner and secret) for
// SessionStoreOptions::ended_retention and at most max_ended_remembered of
// them, oldest forgotten first, so memory stays bounded (~200 B each).
#ifndef FD_SESSION_SESSION_STORE_H_
#define FD_SESSION_SESSION_STORE_H_

#include <cstddef>
#include <deque>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/container/flat_hash_map.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "session/clock.h"
#include "session/end_reason.h"
#include "session/session.h"
#include "session/session_metrics.h"
#include "session/session_state.h"

namespace fd::session {

struct SessionStoreOptions {
  // Live sessions at most, in all / per environment / per client identity.
  size_t max_sessions = 256;
  size_t max_sessions_per_environment = 256;
  size_t max_sessions_per_client = 16;
  // A session with no activity (create, resume, frame begin/end, Touch) and
  // no frame in flight for this long is ended by ExpireIdle() as "expired".
  absl::Duration idle_timeout = absl::Minutes(5);
  // How long, and how many, ended sessions are remembered with their reason.
  absl::Duration ended_retention = absl::Hours(1);
  size_t max_ended_remembered = 10000;
};

// INVALID_ARGUMENT naming the option unless every limit is >= 1 and every
// duration > 0.
absl::Status ValidateSessionStoreOptions(const SessionStoreOptions& options);

// A newly created session and the secret its client needs to resume it
// (SessionOpened.session_id / resume_token).
struct CreatedSession {
  std::shared_ptr<Session> session;
  std::string resume_secret;
};

// What the store remembers about an ended session.
struct EndedSessionInfo {
  EndReason reason;
  std::string detail;  // e.g. the eviction cause; may be empty
  std::string environment;
  absl::Time ended_at;
};

// Ownership: the server owns the store; sessions it hands out are shared.
// Thread-safety: every public method is thread-safe (one internal mutex,
// ordered before each session's mutex); the observer is called after the
// store's mutex is released.
class SessionStore {
 public:
  // INVALID_ARGUMENT for invalid options. `clock` and `observer` (nullptr: a
  // no-op observer) must outlive the store and its sessions.
  static absl::StatusOr<std::unique_ptr<SessionStore>> Create(
      SessionStoreOptions options, const Clock* clock, SessionStoreObserver* observer = nullptr);

  SessionStore(const SessionStore&) = delete;
  SessionStore& operator=(const SessionStore&) = delete;

  // Creates a session owned by `client_identity` (the authenticated client,
  // e.g. the bearer token's subject; all clients of a server without auth
  // may share "", and then share the per-client limit) with `initial_state`
  // (a fresh SessionState, or one from ImportState to continue a session
  // moved from elsewhere). RESOURCE_EXHAUSTED naming the limit and its value
  // when a limit is reached; UNAVAILABLE while draining; INTERNAL if the OS
  // gives no randomness.
  //
  // `preferred_id` (the open's x-session-id, which a sticky load balancer
  // hashed to route the stream here) becomes the session id when it is well
  // formed (IsWellFormedToken) and neither live nor remembered as ended;
  // otherwise a fresh random id is drawn. The resume secret is always ours.
  absl::StatusOr<CreatedSession> Create(std::string client_identity, SessionState initial_state,
                                        std::string_view preferred_id = {})
      ABSL_LOCKS_EXCLUDED(mu_);

  // The live session `session_id` (no ownership check: for the server's own
  // use, e.g. the stream that owns it). NOT_FOUND "unknown session" for an id
  // never seen (or forgotten), NOT_FOUND naming the reason for an ended one
  // (EndReasonFromStatus() recovers it); INVALID_ARGUMENT for a malformed id.
  absl::StatusOr<std::shared_ptr<Session>> Lookup(std::string_view session_id) const
      ABSL_LOCKS_EXCLUDED(mu_);

  // A client re-attaching to its session. Checks ownership before anything
  // else is revealed: PERMISSION_DENIED if `client_identity` is not the
  // session's owner or `resume_secret` is wrong (also for a remembered ended
  // session); then NOT_FOUND as Lookup; UNAVAILABLE while draining. Marks
  // activity.
  absl::StatusOr<std::shared_ptr<Session>> Resume(std::string_view session_id,
                                                  std::string_view resume_secret,
                                                  std::string_view client_identity)
      ABSL_LOCKS_EXCLUDED(mu_);

  // Ends a live session because its client closed it. A frame in flight
  // finishes (its worker holds the session). NOT_FOUND as Lookup otherwise.
  absl::Status Close(std::string_view session_id) ABSL_LOCKS_EXCLUDED(mu_);

  // Ends a live session as "evicted"; `detail` (e.g. "environment removed")
  // is remembered and shown to the client. NOT_FOUND as Lookup otherwise.
  absl::Status Evict(std::string_view session_id, std::string_view detail) ABSL_LOCKS_EXCLUDED(mu_);

  // Evicts every live session of `environment`; returns them (e.g. to cancel
  // their queued frames).
  std::vector<std::shared_ptr<Session>> EvictEnvironment(std::string_view environment,
                                                         std::string_view detail)
      ABSL_LOCKS_EXCLUDED(mu_);

  // Ends every live session as "draining" and refuses new creates and
  // resumes from now on (UNAVAILABLE). Returns the sessions it ended.
  std::vector<std::shared_ptr<Session>> DrainAll() ABSL_LOCKS_EXCLUDED(mu_);

  // Ends every session idle for at least idle_timeout (no frame in flight)
  // as "expired", and forgets ended sessions past their retention. Returns
  // the sessions it ended. Called periodically (SessionReaper).
  std::vector<std::shared_ptr<Session>> ExpireIdle() ABSL_LOCKS_EXCLUDED(mu_);

  // Why `session_id` ended, if the store still remembers it; nullopt for a
  // live or unknown session.
  std::optional<EndedSessionInfo> EndedInfo(std::string_view session_id) const
      ABSL_LOCKS_EXCLUDED(mu_);
  std::optional<EndReason> EndReasonOf(std::string_view session_id) const ABSL_LOCKS_EXCLUDED(mu_);

  size_t live_sessions() const ABSL_LOCKS_EXCLUDED(mu_);
  size_t live_sessions_in(std::string_view environment) const ABSL_LOCKS_EXCLUDED(mu_);
  size_t ended_remembered() const ABSL_LOCKS_EXCLUDED(mu_);
  bool draining() const ABSL_LOCKS_EXCLUDED(mu_);
  const SessionStoreOptions& options() const { return options_; }

 private:
  struct LiveEntry {
    std::shared_ptr<Session> session;
    std::string resume_secret;
  };
  struct EndedEntry {
    EndedSessionInfo info;
    std::string client_identity;
    std::string resume_secret;
  };
  // Observer calls gathered under the lock and made after releasing it.
  struct Event {
    enum Kind { kOpened, kResumed, kEnded, kRejected } kind;
    std::string environment;
    EndReason end_reason = EndReason::kClosed;
    RejectReason reject_reason = RejectReason::kTotalLimit;
  };

  SessionStore(SessionStoreOptions options, const Clock* clock, SessionStoreObserver* observer);

  // Moves a live session to the ended memory and marks it ended.
  void EndLocked(const std::string& session_id, EndReason reason, std::string_view detail,
                 std::vector<Event>* events) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // Forgets ended sessions beyond the retention time or count.
  void PruneEndedLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // NOT_FOUND "unknown session" or naming the reason it ended.
  absl::Status NotLiveErrorLocked(std::string_view session_id) const
      ABSL_SHARED_LOCKS_REQUIRED(mu_);
  // Ends one live session for Close/Evict.
  absl::Status EndOne(std::string_view session_id, EndReason reason, std::string_view detail)
      ABSL_LOCKS_EXCLUDED(mu_);
  void Notify(const std::vector<Event>& events) const;

  const SessionStoreOptions options_;
  const Clock* const clock_;
  SessionStoreObserver* const observer_;

  mutable absl::Mutex mu_;
  bool draining_ ABSL_GUARDED_BY(mu_) = false;
  absl::flat_hash_map<std::string, LiveEntry> live_ ABSL_GUARDED_BY(mu_);
  absl::flat_hash_map<std::string, size_t> live_per_environment_ ABSL_GUARDED_BY(mu_);
  absl::flat_hash_map<std::string, size_t> live_per_client_ ABSL_GUARDED_BY(mu_);
  absl::flat_hash_map<std::string, EndedEntry> ended_ ABSL_GUARDED_BY(mu_);
  // Ids in ended_, oldest first (the order they ended in).
  std::deque<std::string> ended_order_ ABSL_GUARDED_BY(mu_);
};

}  // namespace fd::session

#endif  // FD_SESSION_SESSION_STORE_H_

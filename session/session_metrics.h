// What the session store reports to metrics. The server implements this
// interface (with prometheus counters/gauges); session/ itself must not
// depend on prometheus or gRPC.
#ifndef FD_SESSION_SESSION_METRICS_H_
#define FD_SESSION_SESSION_METRICS_H_

#include <string_view>

#include "session/end_reason.h"

namespace fd::session {

// Why the store refused to create or resume a session.
enum class RejectReason {
  kTotalLimit,        // SessionStoreOptions::max_sessions reached
  kEnvironmentLimit,  // max_sessions_per_environment reached
  kClientLimit,       // max_sessions_per_client reached
  kPermissionDenied,  // resume with a wrong secret or by another client
  kDraining,          // the store is draining
};

// "total_limit", "environment_limit", "client_limit", "permission_denied",
// "draining" (for metric labels).
std::string_view RejectReasonName(RejectReason reason);

// Ownership: the store borrows it; it must outlive the store.
// Thread-safety: methods are called from any thread that calls the store
// (and the reaper thread), concurrently, and never with a store or session
// lock held, so an implementation may call back into the store. They should
// be cheap (counter increments). Live sessions per environment =
// opened - ended (a resume does not change it).
class SessionStoreObserver {
 public:
  virtual ~SessionStoreObserver() = default;
  // A session was created in `environment`.
  virtual void OnOpened(std::string_view environment) {}
  // A live session was resumed by its client.
  virtual void OnResumed(std::string_view environment) {}
  // A live session ended (closed, expired, evicted or drained).
  virtual void OnEnded(std::string_view environment, EndReason reason) {}
  // A create or resume was refused. `environment` is empty when unknown
  // (resume of a session the store does not hold).
  virtual void OnRejected(std::string_view environment, RejectReason reason) {}
};

// Does nothing: the default when the server passes no observer.
class NoopSessionStoreObserver final : public SessionStoreObserver {
 public:
  static SessionStoreObserver* Get() {
    static NoopSessionStoreObserver* const observer = new NoopSessionStoreObserver();
    return observer;
  }
};

}  // namespace fd::session

#endif  // FD_SESSION_SESSION_METRICS_H_

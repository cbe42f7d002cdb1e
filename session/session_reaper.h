// A background thread that calls SessionStore::ExpireIdle() periodically.
//
// It waits on a condition (absl::Mutex::AwaitWithTimeout), never sleeps, so
// Stop() and Kick() wake it at once. Tests give it an infinite interval and
// drive it with Kick() + AwaitPasses(), together with a FakeClock for the
// store: no timing is involved.
#ifndef FD_SESSION_SESSION_REAPER_H_
#define FD_SESSION_SESSION_REAPER_H_

#include <cstdint>
#include <functional>
#include <memory>
#include <thread>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "session/session.h"
#include "session/session_store.h"

namespace fd::session {

// Ownership: borrows the store, which must outlive the reaper.
// Thread-safety: every public method is thread-safe.
class SessionReaper {
 public:
  // Called on the reaper thread, with no lock held, with the sessions one
  // pass expired (possibly none), e.g. to send their streams a notice.
  using ExpiredCallback = std::function<void(const std::vector<std::shared_ptr<Session>>&)>;

  // Starts the thread. It runs a pass every `interval` of real time
  // (absl::InfiniteDuration(): only when kicked) and on every Kick().
  SessionReaper(SessionStore* store, absl::Duration interval, ExpiredCallback on_expired = nullptr);
  // Stops and joins the thread.
  ~SessionReaper();

  SessionReaper(const SessionReaper&) = delete;
  SessionReaper& operator=(const SessionReaper&) = delete;

  // Asks for a pass now (it runs on the reaper thread).
  void Kick() ABSL_LOCKS_EXCLUDED(mu_);
  // Blocks until at least `count` passes have completed since construction;
  // returns the number completed. Returns early (with fewer) after Stop().
  uint64_t AwaitPasses(uint64_t count) ABSL_LOCKS_EXCLUDED(mu_);
  uint64_t passes() const ABSL_LOCKS_EXCLUDED(mu_);
  // Stops the thread and waits for it (idempotent; a pass in progress ends
  // first).
  void Stop() ABSL_LOCKS_EXCLUDED(mu_);

 private:
  void Run() ABSL_LOCKS_EXCLUDED(mu_);

  SessionStore* const store_;
  const absl::Duration interval_;
  const ExpiredCallback on_expired_;

  mutable absl::Mutex mu_;
  bool stop_ ABSL_GUARDED_BY(mu_) = false;
  bool kicked_ ABSL_GUARDED_BY(mu_) = false;
  uint64_t passes_ ABSL_GUARDED_BY(mu_) = 0;

  absl::Mutex join_mu_;  // serialises Stop() callers around the join
  std::thread thread_;
};

}  // namespace fd::session

#endif  // FD_SESSION_SESSION_REAPER_H_

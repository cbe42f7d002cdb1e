// Time source of the session store (idle expiry, how long an ended session
// is remembered), injectable so tests drive expiry with a fake clock
// (tests/testing/fake_clock.h) instead of sleeping.
#ifndef FD_SESSION_CLOCK_H_
#define FD_SESSION_CLOCK_H_

#include "absl/time/clock.h"
#include "absl/time/time.h"

namespace fd::session {

// Ownership: whoever creates a clock keeps it alive longer than every store
// and session that uses it. Thread-safety: Now() may be called from any
// thread concurrently (implementations must allow it).
class Clock {
 public:
  virtual ~Clock() = default;
  virtual absl::Time Now() const = 0;
};

// The system's wall clock (absl::Now()).
class RealClock final : public Clock {
 public:
  absl::Time Now() const override { return absl::Now(); }

  // A process-wide instance (never destroyed).
  static const Clock* Get() {
    static const RealClock* const clock = new RealClock();
    return clock;
  }
};

}  // namespace fd::session

#endif  // FD_SESSION_CLOCK_H_

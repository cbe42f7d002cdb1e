// A manually advanced fd::session::Clock for tests: time moves only when the
// test says so, so expiry is tested without sleeping.
#ifndef FD_TESTS_TESTING_FAKE_CLOCK_H_
#define FD_TESTS_TESTING_FAKE_CLOCK_H_

#include "absl/base/thread_annotations.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "session/clock.h"

namespace fd::testing {

// Thread-safety: every method may be called from any thread.
class FakeClock final : public fd::session::Clock {
 public:
  // Starts at an arbitrary fixed instant (not the epoch, so that "zero time"
  // bugs show).
  explicit FakeClock(absl::Time start = absl::FromUnixSeconds(1'700'000'000)) : now_(start) {}

  absl::Time Now() const override {
    absl::MutexLock lock(&mu_);
    return now_;
  }

  // Moves time forward by `delta` (>= 0).
  void Advance(absl::Duration delta) {
    absl::MutexLock lock(&mu_);
    now_ += delta;
  }

  void Set(absl::Time now) {
    absl::MutexLock lock(&mu_);
    now_ = now;
  }

 private:
  mutable absl::Mutex mu_;
  absl::Time now_ ABSL_GUARDED_BY(mu_);
};

}  // namespace fd::testing

#endif  // FD_TESTS_TESTING_FAKE_CLOCK_H_

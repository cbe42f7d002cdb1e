#include "session/session_reaper.h"

#include <utility>

namespace fd::session {

SessionReaper::SessionReaper(SessionStore* store, absl::Duration interval,
                             ExpiredCallback on_expired)
    : store_(store), interval_(interval), on_expired_(std::move(on_expired)) {
  thread_ = std::thread([this] { Run(); });
}

SessionReaper::~SessionReaper() { Stop(); }

void SessionReaper::Kick() {
  absl::MutexLock lock(&mu_);
  kicked_ = true;
}

uint64_t SessionReaper::AwaitPasses(uint64_t count) {
  absl::MutexLock lock(&mu_);
  auto done = [this, count]() ABSL_SHARED_LOCKS_REQUIRED(mu_) { return passes_ >= count || stop_; };
  mu_.Await(absl::Condition(&done));
  return passes_;
}

uint64_t SessionReaper::passes() const {
  absl::MutexLock lock(&mu_);
  return passes_;
}

void SessionReaper::Stop() {
  {
    absl::MutexLock lock(&mu_);
    stop_ = true;
  }
  absl::MutexLock join_lock(&join_mu_);
  if (thread_.joinable()) thread_.join();
}

void SessionReaper::Run() {
  auto woken = [this]() ABSL_SHARED_LOCKS_REQUIRED(mu_) { return stop_ || kicked_; };
  while (true) {
    {
      absl::MutexLock lock(&mu_);
      // Returns when kicked or stopped, or after `interval_` (a periodic
      // pass); an infinite interval waits for a kick.
      mu_.AwaitWithTimeout(absl::Condition(&woken), interval_);
      if (stop_) return;
      kicked_ = false;
    }
    std::vector<std::shared_ptr<Session>> expired = store_->ExpireIdle();
    if (on_expired_) on_expired_(expired);
    absl::MutexLock lock(&mu_);
    ++passes_;
  }
}

}  // namespace fd::session

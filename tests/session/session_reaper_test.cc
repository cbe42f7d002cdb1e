#include "session/session_reaper.h"

#include <memory>
#include <string>
#include <vector>

#include "absl/synchronization/mutex.h"
#include "gtest/gtest.h"
#include "tests/session/session_test_util.h"
#include "tests/testing/fake_clock.h"

namespace fd::session {
namespace {

using ::fd::session::testing::MakeGBufferOnlyState;

class SessionReaperTest : public ::testing::Test {
 protected:
  void SetUp() override {
    SessionStoreOptions options;
    options.idle_timeout = absl::Minutes(5);
    store_ = *SessionStore::Create(options, &clock_);
  }

  fd::testing::FakeClock clock_;
  std::unique_ptr<SessionStore> store_;
};

// Driven by Kick() and the fake clock only: the interval is infinite, so no
// real time is involved and nothing sleeps.
TEST_F(SessionReaperTest, KickedPassesExpireIdleSessions) {
  absl::Mutex mu;
  std::vector<std::string> expired_ids;
  SessionReaper reaper(store_.get(), absl::InfiniteDuration(),
                       [&](const std::vector<std::shared_ptr<Session>>& expired) {
                         absl::MutexLock lock(&mu);
                         for (const auto& session : expired) expired_ids.push_back(session->id());
                       });
  CreatedSession created = *store_->Create("alice", MakeGBufferOnlyState());

  clock_.Advance(absl::Minutes(4));
  reaper.Kick();
  EXPECT_GE(reaper.AwaitPasses(1), 1u);
  EXPECT_EQ(store_->live_sessions(), 1u);

  clock_.Advance(absl::Minutes(1));
  const uint64_t before = reaper.passes();
  reaper.Kick();
  reaper.AwaitPasses(before + 1);
  EXPECT_EQ(store_->live_sessions(), 0u);
  EXPECT_EQ(created.session->end_reason(), EndReason::kExpired);
  absl::MutexLock lock(&mu);
  ASSERT_EQ(expired_ids.size(), 1u);
  EXPECT_EQ(expired_ids[0], created.session->id());
}

TEST_F(SessionReaperTest, StopWakesTheThreadAndIsIdempotent) {
  SessionReaper reaper(store_.get(), absl::InfiniteDuration());
  reaper.Stop();  // returns although the wait has no timeout
  reaper.Stop();
  const uint64_t passes = reaper.passes();
  EXPECT_EQ(reaper.AwaitPasses(passes + 10), passes);  // no longer blocks
}

TEST_F(SessionReaperTest, DestructorStops) {
  auto reaper = std::make_unique<SessionReaper>(store_.get(), absl::InfiniteDuration());
  reaper->Kick();
  EXPECT_GE(reaper->AwaitPasses(1), 1u);
  reaper.reset();  // joins without hanging (the wait has no timeout)
  EXPECT_EQ(reaper, nullptr);
}

}  // namespace
}  // namespace fd::session

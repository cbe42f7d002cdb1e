#include "session/session_store.h"

#include <atomic>
#include <cstdint>
#include <map>
#include <memory>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "absl/container/flat_hash_set.h"
#include "absl/synchronization/mutex.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "session/random_token.h"
#include "session/state_blob.h"
#include "tests/session/session_test_util.h"
#include "tests/testing/fake_clock.h"

namespace fd::session {
namespace {

using ::fd::session::testing::MakeGBufferOnlyState;
using ::fd::session::testing::MakeImage;
using ::fd::session::testing::MakeSettings;
using ::testing::HasSubstr;

// Records every observer call, for assertions.
class RecordingObserver : public SessionStoreObserver {
 public:
  void OnOpened(std::string_view environment) override {
    Add(absl::StrCat("opened ", ToAbsl(environment)));
  }
  void OnResumed(std::string_view environment) override {
    Add(absl::StrCat("resumed ", ToAbsl(environment)));
  }
  void OnEnded(std::string_view environment, EndReason reason) override {
    Add(absl::StrCat("ended ", ToAbsl(environment), " ", ToAbsl(EndReasonName(reason))));
  }
  void OnRejected(std::string_view environment, RejectReason reason) override {
    Add(absl::StrCat("rejected ", ToAbsl(environment), " ", ToAbsl(RejectReasonName(reason))));
  }
  int Count(const std::string& event) const {
    absl::MutexLock lock(&mu_);
    auto it = counts_.find(event);
    return it == counts_.end() ? 0 : it->second;
  }

 private:
  static absl::string_view ToAbsl(std::string_view s) { return {s.data(), s.size()}; }
  void Add(std::string event) {
    absl::MutexLock lock(&mu_);
    ++counts_[std::move(event)];
  }
  mutable absl::Mutex mu_;
  std::map<std::string, int> counts_ ABSL_GUARDED_BY(mu_);
};

class SessionStoreTest : public ::testing::Test {
 protected:
  void SetUp() override { Reset(SessionStoreOptions{}); }

  void Reset(SessionStoreOptions options) {
    options.idle_timeout = absl::Minutes(5);
    options_ = options;
    store_ = *SessionStore::Create(options, &clock_, &observer_);
  }

  CreatedSession MustCreate(const std::string& client = "alice",
                            const std::string& environment = "downtown_west") {
    absl::StatusOr<CreatedSession> created =
        store_->Create(client, MakeGBufferOnlyState(MakeSettings(environment)));
    EXPECT_TRUE(created.ok()) << created.status();
    return *std::move(created);
  }

  fd::testing::FakeClock clock_;
  RecordingObserver observer_;
  SessionStoreOptions options_;
  std::unique_ptr<SessionStore> store_;
};

TEST_F(SessionStoreTest, OptionsAreValidated) {
  SessionStoreOptions options;
  options.max_sessions_per_client = 0;
  EXPECT_THAT(SessionStore::Create(options, &clock_).status().message(),
              HasSubstr("options.max_sessions_per_client"));
  options = SessionStoreOptions{};
  options.idle_timeout = absl::ZeroDuration();
  EXPECT_THAT(SessionStore::Create(options, &clock_).status().message(),
              HasSubstr("options.idle_timeout"));
  EXPECT_EQ(SessionStore::Create(SessionStoreOptions{}, nullptr).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST_F(SessionStoreTest, CreateGivesRandomIdAndSeparateSecret) {
  CreatedSession created = MustCreate();
  EXPECT_TRUE(IsWellFormedToken(created.session->id())) << created.session->id();
  EXPECT_TRUE(IsWellFormedToken(created.resume_secret));
  EXPECT_NE(created.session->id(), created.resume_secret);
  EXPECT_EQ(created.session->client_identity(), "alice");
  EXPECT_EQ(store_->live_sessions(), 1u);
  EXPECT_EQ(store_->live_sessions_in("downtown_west"), 1u);
  EXPECT_EQ(observer_.Count("opened downtown_west"), 1);
}

TEST_F(SessionStoreTest, AdoptsAWellFormedUnusedPreferredId) {
  const std::string wanted = "0123456789abcdef0123456789abcdef";
  auto first = store_->Create("alice", MakeGBufferOnlyState(MakeSettings()), wanted);
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_EQ(first->session->id(), wanted);
  EXPECT_NE(first->resume_secret, wanted);

  // Taken (live): a fresh id instead.
  auto second = store_->Create("alice", MakeGBufferOnlyState(MakeSettings()), wanted);
  ASSERT_TRUE(second.ok()) << second.status();
  EXPECT_NE(second->session->id(), wanted);
  EXPECT_TRUE(IsWellFormedToken(second->session->id()));

  // Remembered as ended: not reused either (a resume must still say why it ended).
  ASSERT_TRUE(store_->Close(wanted).ok());
  auto third = store_->Create("alice", MakeGBufferOnlyState(MakeSettings()), wanted);
  ASSERT_TRUE(third.ok()) << third.status();
  EXPECT_NE(third->session->id(), wanted);

  // Malformed (upper case, wrong length): ignored.
  for (const char* bad : {"0123456789ABCDEF0123456789ABCDEF", "abc", ""}) {
    auto created = store_->Create("alice", MakeGBufferOnlyState(MakeSettings()), bad);
    ASSERT_TRUE(created.ok()) << created.status();
    EXPECT_NE(created->session->id(), bad);
    EXPECT_TRUE(IsWellFormedToken(created->session->id()));
  }
}

TEST_F(SessionStoreTest, IdsAreUniqueOverManySessions) {
  SessionStoreOptions options;
  options.max_sessions = options.max_sessions_per_environment = options.max_sessions_per_client =
      5000;
  Reset(options);
  absl::flat_hash_set<std::string> ids, secrets;
  for (int i = 0; i < 5000; ++i) {
    CreatedSession created = MustCreate();
    ids.insert(created.session->id());
    secrets.insert(created.resume_secret);
  }
  EXPECT_EQ(ids.size(), 5000u);
  EXPECT_EQ(secrets.size(), 5000u);
}

TEST_F(SessionStoreTest, LookupResumeClose) {
  CreatedSession created = MustCreate();
  const std::string id = created.session->id();

  absl::StatusOr<std::shared_ptr<Session>> found = store_->Lookup(id);
  ASSERT_TRUE(found.ok()) << found.status();
  EXPECT_EQ(found->get(), created.session.get());

  clock_.Advance(absl::Minutes(1));
  absl::StatusOr<std::shared_ptr<Session>> resumed =
      store_->Resume(id, created.resume_secret, "alice");
  ASSERT_TRUE(resumed.ok()) << resumed.status();
  EXPECT_EQ(resumed->get(), created.session.get());
  EXPECT_EQ(created.session->last_activity(), clock_.Now());  // resume is activity
  EXPECT_EQ(observer_.Count("resumed downtown_west"), 1);

  ASSERT_TRUE(store_->Close(id).ok());
  EXPECT_EQ(store_->live_sessions(), 0u);
  EXPECT_EQ(created.session->end_reason(), EndReason::kClosed);
  EXPECT_EQ(observer_.Count("ended downtown_west closed"), 1);
}

TEST_F(SessionStoreTest, UnknownAndMalformedIds) {
  absl::Status unknown = store_->Lookup("0123456789abcdef0123456789abcdef").status();
  EXPECT_EQ(unknown.code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(unknown.message(), HasSubstr("unknown session"));
  EXPECT_FALSE(EndReasonFromStatus(unknown).has_value());
  EXPECT_EQ(store_->Resume("0123456789abcdef0123456789abcdef", "x", "alice").status().code(),
            absl::StatusCode::kNotFound);
  EXPECT_EQ(store_->Close("0123456789abcdef0123456789abcdef").code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(store_->Lookup("not-an-id").status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(store_->Resume("", "", "alice").status().message(), HasSubstr("session_id"));
}

TEST_F(SessionStoreTest, WrongSecretOrOtherClientIsDenied) {
  CreatedSession created = MustCreate("alice");
  const std::string id = created.session->id();
  absl::Status other = store_->Resume(id, created.resume_secret, "mallory").status();
  EXPECT_EQ(other.code(), absl::StatusCode::kPermissionDenied);
  EXPECT_THAT(other.message(), HasSubstr("belongs to another client"));

  std::string wrong = created.resume_secret;
  wrong[31] = wrong[31] == '0' ? '1' : '0';
  for (const std::string& secret : {wrong, std::string(), created.session->id()}) {
    absl::Status status = store_->Resume(id, secret, "alice").status();
    EXPECT_EQ(status.code(), absl::StatusCode::kPermissionDenied);
    EXPECT_THAT(status.message(), HasSubstr("wrong resume_token"));
  }
  EXPECT_EQ(observer_.Count("rejected downtown_west permission_denied"), 4);
  // The denied attempts did not end or change the session.
  EXPECT_TRUE(store_->Resume(id, created.resume_secret, "alice").ok());
}

TEST_F(SessionStoreTest, TotalLimit) {
  SessionStoreOptions options;
  options.max_sessions = 3;
  Reset(options);
  MustCreate("a", "env1");
  MustCreate("b", "env2");
  CreatedSession third = MustCreate("c", "env3");
  absl::Status status = store_->Create("d", MakeGBufferOnlyState(MakeSettings("env4"))).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_THAT(status.message(), HasSubstr("max_sessions = 3"));
  EXPECT_EQ(observer_.Count("rejected env4 total_limit"), 1);
  ASSERT_TRUE(store_->Close(third.session->id()).ok());
  EXPECT_TRUE(store_->Create("d", MakeGBufferOnlyState(MakeSettings("env4"))).ok());
}

TEST_F(SessionStoreTest, PerEnvironmentLimit) {
  SessionStoreOptions options;
  options.max_sessions_per_environment = 2;
  Reset(options);
  MustCreate("a", "hillside");
  MustCreate("b", "hillside");
  absl::Status status =
      store_->Create("c", MakeGBufferOnlyState(MakeSettings("hillside"))).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_THAT(status.message(),
              HasSubstr("max_sessions_per_environment = 2 (environment \"hillside\")"));
  EXPECT_EQ(observer_.Count("rejected hillside environment_limit"), 1);
  EXPECT_TRUE(store_->Create("c", MakeGBufferOnlyState(MakeSettings("city_park"))).ok());
}

TEST_F(SessionStoreTest, PerClientLimit) {
  SessionStoreOptions options;
  options.max_sessions_per_client = 2;
  Reset(options);
  MustCreate("alice", "env1");
  CreatedSession second = MustCreate("alice", "env2");
  absl::Status status =
      store_->Create("alice", MakeGBufferOnlyState(MakeSettings("env3"))).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_THAT(status.message(), HasSubstr("max_sessions_per_client = 2"));
  EXPECT_EQ(observer_.Count("rejected env3 client_limit"), 1);
  EXPECT_TRUE(store_->Create("bob", MakeGBufferOnlyState(MakeSettings("env3"))).ok());
  // Ended sessions no longer count.
  ASSERT_TRUE(store_->Evict(second.session->id(), "test").ok());
  EXPECT_TRUE(store_->Create("alice", MakeGBufferOnlyState(MakeSettings("env3"))).ok());
}

TEST_F(SessionStoreTest, IdleExpiryIsRememberedAsExpired) {
  CreatedSession idle = MustCreate("alice");
  CreatedSession busy = MustCreate("bob");
  CreatedSession active = MustCreate("carol");
  ASSERT_TRUE(busy.session->TryBeginFrame(0).ok());  // a frame in flight, however long

  clock_.Advance(absl::Minutes(4));
  active.session->Touch();
  clock_.Advance(absl::Minutes(1) - absl::Seconds(1));
  EXPECT_TRUE(store_->ExpireIdle().empty());  // 4:59 idle: not yet

  clock_.Advance(absl::Seconds(1));
  std::vector<std::shared_ptr<Session>> expired = store_->ExpireIdle();
  ASSERT_EQ(expired.size(), 1u);
  EXPECT_EQ(expired[0].get(), idle.session.get());
  EXPECT_EQ(idle.session->end_reason(), EndReason::kExpired);
  EXPECT_EQ(store_->live_sessions(), 2u);
  EXPECT_EQ(observer_.Count("ended downtown_west expired"), 1);

  absl::Status lookup = store_->Lookup(idle.session->id()).status();
  EXPECT_EQ(lookup.code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(lookup.message(), HasSubstr("has ended: expired"));
  EXPECT_THAT(lookup.message(), HasSubstr("no activity for 5m"));
  EXPECT_EQ(EndReasonFromStatus(lookup), EndReason::kExpired);
  EXPECT_EQ(store_->EndReasonOf(idle.session->id()), EndReason::kExpired);

  // Its owner resuming is told why.
  absl::Status resume = store_->Resume(idle.session->id(), idle.resume_secret, "alice").status();
  EXPECT_EQ(resume.code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(EndReasonFromStatus(resume), EndReason::kExpired);
  // Anyone else learns nothing about it.
  EXPECT_EQ(store_->Resume(idle.session->id(), idle.resume_secret, "bob").status().code(),
            absl::StatusCode::kPermissionDenied);
  EXPECT_EQ(store_->Resume(idle.session->id(), busy.resume_secret, "alice").status().code(),
            absl::StatusCode::kPermissionDenied);

  // The busy session expires once its frame ends and it idles again.
  ASSERT_TRUE(busy.session->AbortFrame(0).ok());
  clock_.Advance(absl::Minutes(5));
  expired = store_->ExpireIdle();
  EXPECT_EQ(expired.size(), 2u);
  EXPECT_EQ(busy.session->end_reason(), EndReason::kExpired);
}

TEST_F(SessionStoreTest, EveryEndReasonIsRemembered) {
  CreatedSession closed = MustCreate("a", "env1");
  CreatedSession evicted = MustCreate("b", "env1");
  CreatedSession evicted_env = MustCreate("c", "env2");
  CreatedSession drained = MustCreate("d", "env3");

  ASSERT_TRUE(store_->Close(closed.session->id()).ok());
  ASSERT_TRUE(store_->Evict(evicted.session->id(), "over the memory budget").ok());
  std::vector<std::shared_ptr<Session>> by_env =
      store_->EvictEnvironment("env2", "environment removed");
  ASSERT_EQ(by_env.size(), 1u);
  EXPECT_EQ(by_env[0].get(), evicted_env.session.get());
  std::vector<std::shared_ptr<Session>> drained_now = store_->DrainAll();
  ASSERT_EQ(drained_now.size(), 1u);
  EXPECT_TRUE(store_->draining());

  struct Case {
    const CreatedSession* created;
    std::string client;
    EndReason reason;
    std::string text;
  };
  const Case cases[] = {
      {&closed, "a", EndReason::kClosed, "has ended: closed by its client"},
      {&evicted, "b", EndReason::kEvicted, "evicted by the server: over the memory budget"},
      {&evicted_env, "c", EndReason::kEvicted, "evicted by the server: environment removed"},
      {&drained, "d", EndReason::kDraining, "has ended: draining"},
  };
  for (const Case& c : cases) {
    const std::string& id = c.created->session->id();
    EXPECT_EQ(c.created->session->end_reason(), c.reason) << c.text;
    for (absl::Status status :
         {store_->Lookup(id).status(),
          store_->Resume(id, c.created->resume_secret, c.client).status(), store_->Close(id)}) {
      EXPECT_EQ(status.code(), absl::StatusCode::kNotFound);
      EXPECT_THAT(status.message(), HasSubstr(c.text));
      EXPECT_EQ(EndReasonFromStatus(status), c.reason);
    }
    std::optional<EndedSessionInfo> info = store_->EndedInfo(id);
    ASSERT_TRUE(info.has_value());
    EXPECT_EQ(info->reason, c.reason);
    EXPECT_EQ(info->ended_at, clock_.Now());
  }
  EXPECT_EQ(observer_.Count("ended env1 closed"), 1);
  EXPECT_EQ(observer_.Count("ended env1 evicted"), 1);
  EXPECT_EQ(observer_.Count("ended env2 evicted"), 1);
  EXPECT_EQ(observer_.Count("ended env3 draining"), 1);
}

TEST_F(SessionStoreTest, DrainingRefusesNewWork) {
  CreatedSession created = MustCreate();
  store_->DrainAll();
  absl::Status create = store_->Create("alice", MakeGBufferOnlyState()).status();
  EXPECT_EQ(create.code(), absl::StatusCode::kUnavailable);
  EXPECT_THAT(create.message(), HasSubstr("draining"));
  EXPECT_EQ(observer_.Count("rejected downtown_west draining"), 1);
  EXPECT_EQ(store_->Resume("0123456789abcdef0123456789abcdef", "x", "alice").status().code(),
            absl::StatusCode::kUnavailable);
  // A draining server still answers the frames it has read.
  EXPECT_TRUE(created.session->TryBeginFrame(0).ok());
  EXPECT_TRUE(created.session
                  ->CommitFrame(0, MakeImage(created.session->settings(), 1),
                                MakeImage(created.session->settings(), 2))
                  .ok());
}

TEST_F(SessionStoreTest, InFlightFrameKeepsAClosedSessionAlive) {
  CreatedSession created = MustCreate();
  std::shared_ptr<Session> worker_ref = created.session;  // the frame worker's
  created.session.reset();
  ASSERT_TRUE(worker_ref->TryBeginFrame(7).ok());
  ASSERT_TRUE(store_->Close(worker_ref->id()).ok());
  // The running frame completes on the ended session...
  EXPECT_TRUE(worker_ref
                  ->CommitFrame(7, MakeImage(worker_ref->settings(), 1),
                                MakeImage(worker_ref->settings(), 2))
                  .ok());
  EXPECT_EQ(worker_ref->last_frame_index(), 7u);
  // ...but no new frame starts.
  absl::Status next = worker_ref->TryBeginFrame(8);
  EXPECT_EQ(next.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(next.message(), HasSubstr("has ended (closed)"));
}

TEST_F(SessionStoreTest, EndedSessionsAreForgottenAfterRetention) {
  SessionStoreOptions options;
  options.ended_retention = absl::Minutes(30);
  Reset(options);
  CreatedSession created = MustCreate();
  ASSERT_TRUE(store_->Close(created.session->id()).ok());
  clock_.Advance(absl::Minutes(30) - absl::Seconds(1));
  store_->ExpireIdle();
  EXPECT_EQ(store_->EndReasonOf(created.session->id()), EndReason::kClosed);
  clock_.Advance(absl::Seconds(1));
  store_->ExpireIdle();
  EXPECT_EQ(store_->ended_remembered(), 0u);
  absl::Status status = store_->Lookup(created.session->id()).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(status.message(), HasSubstr("unknown session"));
}

TEST_F(SessionStoreTest, EndedSessionsAreBoundedInNumber) {
  SessionStoreOptions options;
  options.max_ended_remembered = 3;
  Reset(options);
  std::vector<std::string> ids;
  for (int i = 0; i < 5; ++i) {
    CreatedSession created = MustCreate();
    ids.push_back(created.session->id());
    ASSERT_TRUE(store_->Close(ids.back()).ok());
  }
  EXPECT_EQ(store_->ended_remembered(), 3u);
  for (int i = 0; i < 2; ++i) {
    EXPECT_THAT(store_->Lookup(ids[i]).status().message(), HasSubstr("unknown session")) << i;
  }
  for (int i = 2; i < 5; ++i) {
    EXPECT_EQ(store_->EndReasonOf(ids[i]), EndReason::kClosed) << i;
  }
}

// Export -> import -> create in another store continues the session: same
// state, and the frame index sequence carries over.
TEST_F(SessionStoreTest, MovedSessionContinues) {
  CreatedSession created = MustCreate();
  Session& session = *created.session;
  for (uint64_t t = 0; t < 3; ++t) {
    ASSERT_TRUE(session.TryBeginFrame(t).ok());
    ASSERT_TRUE(session
                    .CommitFrame(t, MakeImage(session.settings(), 2 * t),
                                 MakeImage(session.settings(), 2 * t + 1))
                    .ok());
  }
  std::string blob = *session.ExportState();

  fd::testing::FakeClock other_clock;
  std::unique_ptr<SessionStore> other = *SessionStore::Create(SessionStoreOptions{}, &other_clock);
  absl::StatusOr<SessionState> state = ImportState(blob);
  ASSERT_TRUE(state.ok()) << state.status();
  absl::StatusOr<CreatedSession> moved = other->Create("alice", *std::move(state));
  ASSERT_TRUE(moved.ok()) << moved.status();
  EXPECT_EQ(moved->session->StateSnapshot(), session.StateSnapshot());
  EXPECT_EQ(moved->session->TryBeginFrame(2).code(), absl::StatusCode::kFailedPrecondition);
  ASSERT_TRUE(moved->session->TryBeginFrame(3).ok());
  ASSERT_TRUE(session.TryBeginFrame(3).ok());
  uint64_t seed_moved = 0, seed_original = 1;
  ASSERT_TRUE(
      moved->session->ReadFrameContext(3, [&](const FrameContext& c) { seed_moved = c.frame_seed; })
          .ok());
  ASSERT_TRUE(
      session.ReadFrameContext(3, [&](const FrameContext& c) { seed_original = c.frame_seed; })
          .ok());
  EXPECT_EQ(seed_moved, seed_original);
}

// Many threads create, look up (their own and each other's sessions),
// resume, run frames on and close sessions while another thread advances the
// clock and expires idle ones. Built with -fsanitize=thread this checks for
// data races; here it checks that the bookkeeping stays consistent.
TEST_F(SessionStoreTest, ConcurrentUse) {
  SessionStoreOptions options;
  options.max_sessions = 48;
  options.max_sessions_per_environment = 32;
  options.max_sessions_per_client = 12;
  // Nothing is forgotten during the test, so every ended session is
  // reported with its reason (forgetting is tested above).
  options.max_ended_remembered = 1'000'000;
  options.ended_retention = absl::Hours(1'000'000);
  Reset(options);
  constexpr int kThreads = 6;
  constexpr int kIterations = 400;
  std::atomic<int> created{0}, closed{0}, limited{0};
  std::atomic<bool> stop_reaper{false};
  absl::Mutex ids_mu;
  std::vector<std::string> ids;  // every id created, for cross-thread lookups

  std::thread reaper([&] {
    while (!stop_reaper.load()) {
      clock_.Advance(absl::Minutes(1));
      store_->ExpireIdle();
      std::this_thread::yield();
    }
  });
  std::vector<std::thread> workers;
  for (int t = 0; t < kThreads; ++t) {
    workers.emplace_back([&, t] {
      const std::string client = absl::StrCat("client", t % 3);
      const std::string environment = absl::StrCat("env", t % 2);
      for (int i = 0; i < kIterations; ++i) {
        if (i % 16 == 15) {  // workers expire sessions too, concurrently
          clock_.Advance(absl::Minutes(1));
          store_->ExpireIdle();
        }
        absl::StatusOr<CreatedSession> made =
            store_->Create(client, MakeGBufferOnlyState(MakeSettings(environment, 8, 8)));
        if (!made.ok()) {
          ASSERT_EQ(made.status().code(), absl::StatusCode::kResourceExhausted) << made.status();
          ++limited;
          continue;
        }
        ++created;
        const std::string id = made->session->id();
        std::string other_id;
        {
          absl::MutexLock lock(&ids_mu);
          ids.push_back(id);
          other_id = ids[(i * 7919u + t) % ids.size()];
        }
        // Any session ever created is live or remembered with its reason.
        absl::StatusOr<std::shared_ptr<Session>> other = store_->Lookup(other_id);
        if (!other.ok()) {
          ASSERT_TRUE(EndReasonFromStatus(other.status()).has_value()) << other.status();
        }
        absl::StatusOr<std::shared_ptr<Session>> resumed =
            store_->Resume(id, made->resume_secret, client);
        if (!resumed.ok()) {  // the reaper may have expired it already
          ASSERT_EQ(EndReasonFromStatus(resumed.status()), EndReason::kExpired) << resumed.status();
          continue;
        }
        if ((*resumed)->TryBeginFrame(i).ok()) {
          const SessionSettings& s = (*resumed)->settings();
          ASSERT_TRUE((*resumed)->CommitFrame(i, MakeImage(s, i), MakeImage(s, i + 1)).ok());
        }
        if (i % 8 != 7) {  // every 8th session is left to the reaper
          absl::Status close = store_->Close(id);
          if (close.ok()) {
            ++closed;
          } else {
            ASSERT_EQ(EndReasonFromStatus(close), EndReason::kExpired) << close;
          }
        }
      }
    });
  }
  for (std::thread& worker : workers) worker.join();
  stop_reaper = true;
  reaper.join();

  EXPECT_GT(created.load(), 0);
  EXPECT_EQ(observer_.Count("opened env0") + observer_.Count("opened env1"), created.load());
  EXPECT_EQ(observer_.Count("ended env0 closed") + observer_.Count("ended env1 closed"),
            closed.load());
  const int ended = observer_.Count("ended env0 closed") + observer_.Count("ended env1 closed") +
                    observer_.Count("ended env0 expired") + observer_.Count("ended env1 expired");
  EXPECT_EQ(static_cast<int>(store_->live_sessions()), created.load() - ended);
  EXPECT_EQ(store_->live_sessions_in("env0") + store_->live_sessions_in("env1"),
            store_->live_sessions());
  EXPECT_EQ(static_cast<int>(store_->ended_remembered()), ended);
  EXPECT_EQ(observer_.Count("rejected env0 client_limit") +
                observer_.Count("rejected env1 client_limit") +
                observer_.Count("rejected env0 environment_limit") +
                observer_.Count("rejected env1 environment_limit") +
                observer_.Count("rejected env0 total_limit") +
                observer_.Count("rejected env1 total_limit"),
            limited.load());
  // How much of each path this run took (thread timing decides), in the XML
  // report.
  RecordProperty("created", created.load());
  RecordProperty("closed", closed.load());
  RecordProperty("expired", ended - closed.load());
  RecordProperty("limited", limited.load());
}

}  // namespace
}  // namespace fd::session

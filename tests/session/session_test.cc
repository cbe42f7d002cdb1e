#include "session/session.h"

#include <cstdint>
#include <optional>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "session/frame_seed.h"
#include "session/state_blob.h"
#include "tests/session/session_test_util.h"
#include "tests/testing/fake_clock.h"

namespace fd::session {
namespace {

using ::fd::session::testing::MakeGBufferOnlyState;
using ::fd::session::testing::MakeImage;
using ::fd::session::testing::MakeSettings;
using ::testing::HasSubstr;

constexpr char kId[] = "00112233445566778899aabbccddeeff";

class SessionTest : public ::testing::Test {
 protected:
  fd::testing::FakeClock clock_;
  SessionSettings settings_ = MakeSettings();
};

TEST_F(SessionTest, OneFrameInFlight) {
  Session session(kId, "alice", MakeGBufferOnlyState(settings_), &clock_);
  EXPECT_EQ(session.id(), kId);
  EXPECT_EQ(session.client_identity(), "alice");
  EXPECT_EQ(session.environment(), "downtown_west");
  ASSERT_TRUE(session.TryBeginFrame(1).ok());
  EXPECT_EQ(session.frame_in_flight(), 1u);

  absl::Status second = session.TryBeginFrame(2);
  EXPECT_EQ(second.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(second.message(), HasSubstr("frame 1 of this session is still in flight"));

  ASSERT_TRUE(session.CommitFrame(1, MakeImage(settings_, 1), MakeImage(settings_, 2)).ok());
  EXPECT_FALSE(session.frame_in_flight().has_value());
  EXPECT_EQ(session.last_frame_index(), 1u);
  EXPECT_TRUE(session.TryBeginFrame(2).ok());
}

TEST_F(SessionTest, FrameIndexMustIncreaseStrictly) {
  Session session(kId, "alice", MakeGBufferOnlyState(settings_), &clock_);
  ASSERT_TRUE(session.TryBeginFrame(10).ok());
  ASSERT_TRUE(session.CommitFrame(10, MakeImage(settings_, 1), MakeImage(settings_, 2)).ok());
  for (uint64_t index : {10u, 9u, 0u}) {
    absl::Status status = session.TryBeginFrame(index);
    EXPECT_EQ(status.code(), absl::StatusCode::kFailedPrecondition) << index;
    EXPECT_THAT(status.message(), HasSubstr("greater than the last rendered frame's (10)"));
  }
  EXPECT_TRUE(session.TryBeginFrame(12).ok());  // gaps are fine
}

TEST_F(SessionTest, AbortLeavesStateUnchangedAndAllowsRetry) {
  Session session(kId, "alice", MakeGBufferOnlyState(settings_), &clock_);
  ASSERT_TRUE(session.TryBeginFrame(1).ok());
  ASSERT_TRUE(session.CommitFrame(1, MakeImage(settings_, 1), MakeImage(settings_, 2)).ok());
  const SessionState before = session.StateSnapshot();

  ASSERT_TRUE(session.TryBeginFrame(2).ok());
  uint64_t first_seed = 0;
  ASSERT_TRUE(
      session.ReadFrameContext(2, [&](const FrameContext& c) { first_seed = c.frame_seed; }).ok());
  ASSERT_TRUE(session.AbortFrame(2).ok());
  EXPECT_EQ(session.StateSnapshot(), before);

  // The client retries frame 2: same noise seed, since nothing was rendered.
  ASSERT_TRUE(session.TryBeginFrame(2).ok());
  uint64_t retry_seed = 0;
  ASSERT_TRUE(
      session.ReadFrameContext(2, [&](const FrameContext& c) { retry_seed = c.frame_seed; }).ok());
  EXPECT_EQ(retry_seed, first_seed);
  EXPECT_EQ(retry_seed, FrameSeed(settings_.seed, 1));
}

TEST_F(SessionTest, WrongFrameIndexForContextCommitAbort) {
  Session session(kId, "alice", MakeGBufferOnlyState(settings_), &clock_);
  auto ignore = [](const FrameContext&) {};
  EXPECT_EQ(session.ReadFrameContext(1, ignore).code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(session.AbortFrame(1).code(), absl::StatusCode::kFailedPrecondition);
  ASSERT_TRUE(session.TryBeginFrame(1).ok());
  EXPECT_EQ(session.ReadFrameContext(2, ignore).code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(session.CommitFrame(2, MakeImage(settings_, 1), MakeImage(settings_, 2)).code(),
            absl::StatusCode::kFailedPrecondition);
  // A wrongly sized output keeps the frame in flight, so it can be aborted.
  EXPECT_EQ(session.CommitFrame(1, {}, MakeImage(settings_, 2)).code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(session.frame_in_flight(), 1u);
  EXPECT_TRUE(session.AbortFrame(1).ok());
}

// Continuity bookkeeping: frame t is conditioned on frame t-1's committed
// output and basecolor, with seed FrameSeed(seed, t).
TEST_F(SessionTest, ContextFollowsTheChain) {
  Session session(kId, "alice", MakeGBufferOnlyState(settings_), &clock_);
  ASSERT_TRUE(session.TryBeginFrame(0).ok());
  ASSERT_TRUE(session
                  .ReadFrameContext(0,
                                    [&](const FrameContext& c) {
                                      EXPECT_TRUE(c.previous_frame.empty());  // G-buffer only
                                      EXPECT_TRUE(c.previous_basecolor.empty());
                                      EXPECT_EQ(c.frame_counter, 0u);
                                      EXPECT_EQ(c.frame_seed, FrameSeed(settings_.seed, 0));
                                      EXPECT_FALSE(c.reseeded);
                                    })
                  .ok());
  ASSERT_TRUE(session.CommitFrame(0, MakeImage(settings_, 1), MakeImage(settings_, 2)).ok());
  for (uint64_t t = 1; t < 4; ++t) {
    ASSERT_TRUE(session.TryBeginFrame(t).ok());
    ASSERT_TRUE(
        session
            .ReadFrameContext(t,
                              [&](const FrameContext& c) {
                                EXPECT_EQ(c.previous_frame, MakeImage(settings_, 2 * t - 1));
                                EXPECT_EQ(c.previous_basecolor, MakeImage(settings_, 2 * t));
                                EXPECT_EQ(c.frame_counter, t);
                                EXPECT_EQ(c.frame_seed, FrameSeed(settings_.seed, t));
                              })
            .ok());
    ASSERT_TRUE(
        session.CommitFrame(t, MakeImage(settings_, 2 * t + 1), MakeImage(settings_, 2 * t + 2))
            .ok());
  }
}

TEST_F(SessionTest, KeyframeReseedRestartsTheChainForOneFrame) {
  Session session(kId, "alice", MakeGBufferOnlyState(settings_), &clock_);
  ASSERT_TRUE(session.TryBeginFrame(0).ok());
  ASSERT_TRUE(session.CommitFrame(0, MakeImage(settings_, 1), MakeImage(settings_, 2)).ok());

  // Camera cut: frame 1 carries a keyframe without a basecolor.
  ASSERT_TRUE(session.TryBeginFrame(1, Keyframe{MakeImage(settings_, 50), {}}).ok());
  EXPECT_GT(session.MemoryBytes(), session.StateSnapshot().MemoryBytes());
  ASSERT_TRUE(session
                  .ReadFrameContext(1,
                                    [&](const FrameContext& c) {
                                      EXPECT_TRUE(c.reseeded);
                                      EXPECT_EQ(c.previous_frame, MakeImage(settings_, 50));
                                      EXPECT_TRUE(c.previous_basecolor.empty());
                                      EXPECT_EQ(c.frame_seed, FrameSeed(settings_.seed, 1));
                                    })
                  .ok());
  // If the re-seeded frame fails, the keyframe is forgotten with it.
  ASSERT_TRUE(session.AbortFrame(1).ok());
  ASSERT_TRUE(session.TryBeginFrame(1).ok());
  ASSERT_TRUE(session
                  .ReadFrameContext(1,
                                    [&](const FrameContext& c) {
                                      EXPECT_FALSE(c.reseeded);
                                      EXPECT_EQ(c.previous_frame, MakeImage(settings_, 1));
                                    })
                  .ok());
  ASSERT_TRUE(session.AbortFrame(1).ok());

  // Re-seeded with a basecolor and committed: the next frame chains from the
  // re-seeded frame's output.
  ASSERT_TRUE(
      session.TryBeginFrame(1, Keyframe{MakeImage(settings_, 50), MakeImage(settings_, 51)}).ok());
  ASSERT_TRUE(session
                  .ReadFrameContext(1,
                                    [&](const FrameContext& c) {
                                      EXPECT_EQ(c.previous_basecolor, MakeImage(settings_, 51));
                                    })
                  .ok());
  ASSERT_TRUE(session.CommitFrame(1, MakeImage(settings_, 60), MakeImage(settings_, 61)).ok());
  ASSERT_TRUE(session.TryBeginFrame(2).ok());
  ASSERT_TRUE(session
                  .ReadFrameContext(2,
                                    [&](const FrameContext& c) {
                                      EXPECT_FALSE(c.reseeded);
                                      EXPECT_EQ(c.previous_frame, MakeImage(settings_, 60));
                                      EXPECT_EQ(c.previous_basecolor, MakeImage(settings_, 61));
                                    })
                  .ok());
}

TEST_F(SessionTest, ReseedSizeIsChecked) {
  Session session(kId, "alice", MakeGBufferOnlyState(settings_), &clock_);
  absl::Status status =
      session.TryBeginFrame(0, Keyframe{ImageBuffer(5, 1, 1, PixelType::kUint8), {}});
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(status.message(), HasSubstr("keyframe: expected"));
  status = session.TryBeginFrame(
      0, Keyframe{MakeImage(settings_, 1), ImageBuffer(5, 1, 1, PixelType::kUint8)});
  EXPECT_THAT(status.message(), HasSubstr("keyframe_basecolor: expected"));
  EXPECT_FALSE(session.frame_in_flight().has_value());
}

TEST_F(SessionTest, ActivityAndIdleness) {
  Session session(kId, "alice", MakeGBufferOnlyState(settings_), &clock_);
  const absl::Time created = clock_.Now();
  EXPECT_EQ(session.last_activity(), created);
  clock_.Advance(absl::Seconds(30));
  EXPECT_TRUE(session.IsIdle(clock_.Now(), absl::Seconds(30)));
  EXPECT_FALSE(session.IsIdle(clock_.Now(), absl::Seconds(31)));
  ASSERT_TRUE(session.TryBeginFrame(0).ok());
  EXPECT_EQ(session.last_activity(), clock_.Now());
  clock_.Advance(absl::Hours(1));
  // A frame in flight is never idle, however long it takes.
  EXPECT_FALSE(session.IsIdle(clock_.Now(), absl::Seconds(1)));
  ASSERT_TRUE(session.AbortFrame(0).ok());
  EXPECT_FALSE(session.IsIdle(clock_.Now(), absl::Seconds(1)));
  clock_.Advance(absl::Seconds(5));
  session.Touch();
  EXPECT_EQ(session.last_activity(), clock_.Now());
}

TEST_F(SessionTest, ExportMatchesSnapshot) {
  Session session(kId, "alice", MakeGBufferOnlyState(settings_), &clock_);
  ASSERT_TRUE(session.TryBeginFrame(3).ok());
  ASSERT_TRUE(session.CommitFrame(3, MakeImage(settings_, 1), MakeImage(settings_, 2)).ok());
  ASSERT_TRUE(session.TryBeginFrame(4).ok());  // in flight: not part of the export
  absl::StatusOr<std::string> blob = session.ExportState();
  ASSERT_TRUE(blob.ok()) << blob.status();
  absl::StatusOr<SessionState> imported = ImportState(*blob);
  ASSERT_TRUE(imported.ok()) << imported.status();
  EXPECT_EQ(*imported, session.StateSnapshot());
  EXPECT_EQ(imported->last_frame_index(), 3u);
}

}  // namespace
}  // namespace fd::session

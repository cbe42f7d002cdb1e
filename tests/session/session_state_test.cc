#include "session/session_state.h"

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "session/frame_seed.h"
#include "session/state_blob.h"
#include "tests/session/session_test_util.h"

namespace fd::session {
namespace {

using ::fd::session::testing::MakeImage;
using ::fd::session::testing::MakeSettings;
using ::testing::HasSubstr;

TEST(SessionStateTest, GBufferOnlyStartHasNoPreviousFrame) {
  absl::StatusOr<SessionState> state = SessionState::StartFromGBufferOnly(MakeSettings());
  ASSERT_TRUE(state.ok()) << state.status();
  EXPECT_EQ(state->start_mode(), StartMode::kGBufferOnly);
  EXPECT_FALSE(state->has_previous_frame());
  EXPECT_FALSE(state->has_previous_basecolor());
  EXPECT_EQ(state->frame_counter(), 0u);
  EXPECT_FALSE(state->last_frame_index().has_value());
  EXPECT_EQ(state->NextFrameSeed(), FrameSeed(42, 0));
}

TEST(SessionStateTest, KeyframeStart) {
  const SessionSettings s = MakeSettings();
  const ImageBuffer keyframe = MakeImage(s, 1);
  const ImageBuffer basecolor = MakeImage(s, 2);
  absl::StatusOr<SessionState> state = SessionState::StartFromKeyframe(s, keyframe, basecolor);
  ASSERT_TRUE(state.ok()) << state.status();
  EXPECT_EQ(state->start_mode(), StartMode::kKeyframe);
  EXPECT_EQ(state->previous_frame(), keyframe);
  EXPECT_EQ(state->previous_basecolor(), basecolor);

  // Without a basecolor: the first frame's own basecolor is used.
  absl::StatusOr<SessionState> no_basecolor = SessionState::StartFromKeyframe(s, keyframe, {});
  ASSERT_TRUE(no_basecolor.ok()) << no_basecolor.status();
  EXPECT_TRUE(no_basecolor->has_previous_frame());
  EXPECT_FALSE(no_basecolor->has_previous_basecolor());
}

TEST(SessionStateTest, KeyframeSizeIsChecked) {
  const SessionSettings s = MakeSettings();
  const ImageBuffer small(s.width - 1, s.height, 3, PixelType::kUint8);
  absl::StatusOr<SessionState> state = SessionState::StartFromKeyframe(s, small, {});
  EXPECT_EQ(state.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(state.status().message(), HasSubstr("keyframe: expected 6144 bytes (64 x 32 x 3"));

  state = SessionState::StartFromKeyframe(s, {}, {});
  EXPECT_EQ(state.status().code(), absl::StatusCode::kInvalidArgument);

  state = SessionState::StartFromKeyframe(s, MakeImage(s, 1), small);
  EXPECT_EQ(state.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(state.status().message(), HasSubstr("keyframe_basecolor"));
}

TEST(SessionStateTest, SettingsAreValidated) {
  SessionSettings s = MakeSettings();
  s.width = 0;
  EXPECT_THAT(SessionState::StartFromGBufferOnly(s).status().message(),
              HasSubstr("settings.width"));
  s = MakeSettings();
  s.height = kMaxImageSide + 1;
  EXPECT_THAT(SessionState::StartFromGBufferOnly(s).status().message(),
              HasSubstr("settings.height"));
  s = MakeSettings();
  s.environment.clear();
  EXPECT_THAT(SessionState::StartFromGBufferOnly(s).status().message(),
              HasSubstr("settings.environment"));
  s = MakeSettings();
  s.steps = 0;
  EXPECT_THAT(SessionState::StartFromGBufferOnly(s).status().message(),
              HasSubstr("settings.steps"));
  s = MakeSettings();
  s.scheduler = static_cast<SchedulerKind>(9);
  EXPECT_THAT(SessionState::StartFromGBufferOnly(s).status().message(),
              HasSubstr("settings.scheduler"));
  s = MakeSettings();
  s.sky_mode = static_cast<SkyMode>(0);
  EXPECT_THAT(SessionState::StartFromGBufferOnly(s).status().message(),
              HasSubstr("settings.sky_mode"));
  s = MakeSettings();
  s.output_dtype = static_cast<OutputDType>(4);
  EXPECT_THAT(SessionState::StartFromGBufferOnly(s).status().message(),
              HasSubstr("settings.output_dtype"));
  s = MakeSettings();
  s.output_compression = static_cast<OutputCompression>(2);
  EXPECT_THAT(SessionState::StartFromGBufferOnly(s).status().message(),
              HasSubstr("settings.output_compression"));
}

TEST(SessionStateTest, CommitChainsFrames) {
  const SessionSettings s = MakeSettings();
  SessionState state = *SessionState::StartFromGBufferOnly(s);
  ASSERT_TRUE(state.CommitFrame(5, MakeImage(s, 10), MakeImage(s, 11)).ok());
  EXPECT_EQ(state.frame_counter(), 1u);
  EXPECT_EQ(state.last_frame_index(), 5u);
  EXPECT_EQ(state.previous_frame(), MakeImage(s, 10));
  EXPECT_EQ(state.previous_basecolor(), MakeImage(s, 11));
  EXPECT_EQ(state.NextFrameSeed(), FrameSeed(s.seed, 1));

  // Gaps in frame_index are allowed; going back or repeating is not.
  ASSERT_TRUE(state.CommitFrame(9, MakeImage(s, 12), MakeImage(s, 13)).ok());
  for (uint64_t stale : {9u, 3u}) {
    absl::Status status = state.CommitFrame(stale, MakeImage(s, 14), MakeImage(s, 15));
    EXPECT_EQ(status.code(), absl::StatusCode::kFailedPrecondition);
    EXPECT_THAT(status.message(), HasSubstr("greater than the last rendered frame's (9)"));
  }
  // A rejected commit leaves the state unchanged.
  absl::Status wrong_size =
      state.CommitFrame(10, ImageBuffer(1, 1, 3, PixelType::kUint8), MakeImage(s, 15));
  EXPECT_EQ(wrong_size.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(wrong_size.message(), HasSubstr("output: expected"));
  EXPECT_EQ(state.frame_counter(), 2u);
  EXPECT_EQ(state.last_frame_index(), 9u);
  EXPECT_EQ(state.previous_frame(), MakeImage(s, 12));
}

// "previous_latent": "reuse": a commit may carry the frame's latent; the next
// commit replaces it (an empty one clears it); it counts in MemoryBytes and
// is not exported (an imported session encodes its previous frame once).
TEST(SessionStateTest, CommitKeepsTheLatentOnlyUntilTheNextCommit) {
  const SessionSettings s = MakeSettings();
  SessionState state = *SessionState::StartFromGBufferOnly(s);
  ASSERT_TRUE(state.CommitFrame(1, MakeImage(s, 8), MakeImage(s, 9)).ok());
  const size_t without = state.MemoryBytes();  // two images, no latent
  LatentBuffer latent;
  latent.channels = 4;
  latent.height = s.height / 8;
  latent.width = s.width / 8;
  latent.values =
      std::make_shared<const std::vector<float>>(4 * latent.height * latent.width, 0.5f);
  ASSERT_TRUE(state.CommitFrame(2, MakeImage(s, 10), MakeImage(s, 11), latent).ok());
  EXPECT_EQ(state.previous_latent(), latent);
  EXPECT_EQ(state.MemoryBytes(), without + latent.size_bytes());

  absl::StatusOr<std::string> blob = ExportState(state);
  ASSERT_TRUE(blob.ok()) << blob.status();
  absl::StatusOr<SessionState> imported = ImportState(*blob);
  ASSERT_TRUE(imported.ok()) << imported.status();
  EXPECT_TRUE(imported->previous_latent().empty());
  EXPECT_EQ(imported->previous_frame(), state.previous_frame());

  // Values that do not fill the shape: refused, the state unchanged.
  LatentBuffer short_latent = latent;
  short_latent.values = std::make_shared<const std::vector<float>>(3, 0.f);
  absl::Status bad = state.CommitFrame(3, MakeImage(s, 12), MakeImage(s, 13), short_latent);
  EXPECT_EQ(bad.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(bad.message(), HasSubstr("latent: 3 values for a 4 x 4 x 8 latent"));
  EXPECT_EQ(state.previous_latent(), latent);
  EXPECT_EQ(state.frame_counter(), 2u);

  ASSERT_TRUE(state.CommitFrame(3, MakeImage(s, 12), MakeImage(s, 13)).ok());
  EXPECT_TRUE(state.previous_latent().empty());
  EXPECT_EQ(state.MemoryBytes(), without);
}

TEST(SessionStateTest, RestoreChecksInvariants) {
  const SessionSettings s = MakeSettings();
  EXPECT_TRUE(SessionState::Restore(s, StartMode::kGBufferOnly, 0, std::nullopt, {}, {}).ok());
  EXPECT_TRUE(
      SessionState::Restore(s, StartMode::kKeyframe, 3, 7, MakeImage(s, 1), MakeImage(s, 2)).ok());
  // A keyframe start or a rendered frame needs a previous frame.
  EXPECT_THAT(
      SessionState::Restore(s, StartMode::kKeyframe, 0, std::nullopt, {}, {}).status().message(),
      HasSubstr("previous_frame: required"));
  EXPECT_THAT(SessionState::Restore(s, StartMode::kGBufferOnly, 1, 0, {}, {}).status().message(),
              HasSubstr("previous_frame: required"));
  EXPECT_THAT(
      SessionState::Restore(s, StartMode::kGBufferOnly, 0, std::nullopt, {}, MakeImage(s, 2))
          .status()
          .message(),
      HasSubstr("previous_basecolor: present without"));
  EXPECT_THAT(SessionState::Restore(s, StartMode::kKeyframe, 2, std::nullopt, MakeImage(s, 1), {})
                  .status()
                  .message(),
              HasSubstr("last_frame_index"));
  EXPECT_THAT(
      SessionState::Restore(s, StartMode::kKeyframe, 0, 4, MakeImage(s, 1), {}).status().message(),
      HasSubstr("last_frame_index"));
  EXPECT_THAT(SessionState::Restore(s, static_cast<StartMode>(7), 0, std::nullopt, {}, {})
                  .status()
                  .message(),
              HasSubstr("start_mode"));
}

// The budget: an idle session at 512x512 holds at most 2 MB. Counted
// from the object's actual buffers after a few frames.
TEST(SessionStateTest, IdleStateAt512IsUnder2MB) {
  const SessionSettings s = MakeSettings("downtown_west", 512, 512);
  SessionState state = *SessionState::StartFromKeyframe(s, MakeImage(s, 1), MakeImage(s, 2));
  for (uint64_t i = 0; i < 3; ++i) {
    ASSERT_TRUE(state.CommitFrame(i, MakeImage(s, 10 + i), MakeImage(s, 20 + i)).ok());
  }
  const size_t bytes = state.MemoryBytes();
  EXPECT_GE(bytes, 2u * 512 * 512 * 3);  // the two images are really held
  EXPECT_LT(bytes, 2'000'000u) << "state holds " << bytes << " bytes";
  EXPECT_LT(bytes, 2u * 512 * 512 * 3 + 1024) << "nothing but the two images is large";
}

}  // namespace
}  // namespace fd::session

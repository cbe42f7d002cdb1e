// Server lifecycle: graceful drain with frames in flight, idle expiry and
// eviction notices, and the model repository (load, add, remove, reload at
// run time without disturbing other sessions).
#include <grpcpp/grpcpp.h>

#include <filesystem>
#include <fstream>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "absl/synchronization/notification.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/server/server_test_util.h"
#include "tests/testing/fake_clock.h"
#include "tests/testing/scripted_frame_pipeline.h"

namespace fd::server {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;
using namespace ::fd::server::testing;  // NOLINT(build/namespaces)

// Reads the SessionOpened answer of `stream` after writing `first`.
v1::SessionOpened OpenOn(StreamClient& stream, const v1::RenderRequest& first) {
  EXPECT_TRUE(stream.Write(first));
  std::optional<v1::RenderResponse> opened = stream.Read();
  EXPECT_TRUE(opened.has_value() && opened->has_opened())
      << (opened.has_value() ? opened->DebugString() : "end of stream");
  return opened.has_value() ? opened->opened() : v1::SessionOpened();
}

// A server on the tiny environment whose denoising step call number
// `gated_call` blocks until `gate` opens (GatedStep); `server` is null if it
// did not start.
struct GatedServer {
  std::shared_ptr<fd::testing::Gate> gate = std::make_shared<fd::testing::Gate>();
  std::shared_ptr<absl::Notification> stepping = std::make_shared<absl::Notification>();
  std::unique_ptr<FrameDiffuserServer> server;
};

GatedServer StartGated(int gated_call) {
  GatedServer gated;
  ServerOptions options;
  options.config = TestConfig();
  options.environments.emplace_back(kEmbeddedEnvironmentName, TinyEnvironment());
  options.pipeline_factory = GatedStep(gated.gate, gated.stepping, gated_call);
  gated.server = StartOrNull(std::move(options));
  return gated;
}

// Opens a session on one stream and sends frame 0, which the gated step
// holds; resumes the session on `resumed` meanwhile; checks that the old
// stream is taken over (ABORTED) before the resume is answered; then lets
// the held step go and returns the resume answer (nullopt on failure).
std::optional<v1::SessionOpened> ResumeWhileTheFrameIsHeld(GatedServer& gated,
                                                           StreamClient& resumed) {
  StreamClient broken(Connect(*gated.server));
  const v1::SessionOpened opened = OpenOn(broken, MakeOpen());
  EXPECT_TRUE(broken.Write(MakeFrame(0)));
  gated.stepping->WaitForNotification();
  EXPECT_TRUE(resumed.Write(MakeResume(opened.session_id(), opened.resume_token())));
  broken.ReadAll();
  EXPECT_EQ(broken.Finish().error_code(), grpc::StatusCode::ABORTED);
  gated.gate->Open();
  std::optional<v1::RenderResponse> answer = resumed.Read();
  EXPECT_TRUE(answer.has_value() && answer->has_opened())
      << (answer.has_value() ? answer->DebugString() : "end of stream");
  if (!answer.has_value() || !answer->has_opened()) return std::nullopt;
  return answer->opened();
}

TEST(LifecycleTest, ShutdownDrainsFramesInFlightAndEndsStreamsWithUnavailable) {
  // The first denoising step blocks until the test lets it go, so a frame
  // is provably in flight when the drain starts.
  GatedServer gated = StartGated(/*gated_call=*/0);
  const std::shared_ptr<fd::testing::Gate>& gate = gated.gate;
  const std::shared_ptr<absl::Notification>& stepping = gated.stepping;
  const std::unique_ptr<FrameDiffuserServer>& server = gated.server;
  ASSERT_NE(server, nullptr);

  StreamClient busy(Connect(*server));
  OpenOn(busy, MakeOpen());
  StreamClient idle(Connect(*server));
  OpenOn(idle, MakeOpen());
  ASSERT_TRUE(busy.Write(MakeFrame(0)));
  stepping->WaitForNotification();

  std::thread shutdown([&] { server->Shutdown(absl::Seconds(60)); });

  // Both streams hear about the drain first.
  std::optional<v1::RenderResponse> notice = busy.Read();
  ASSERT_TRUE(notice.has_value() && notice->has_notice());
  EXPECT_EQ(notice->notice().reason(), v1::SessionNotice::REASON_DRAINING);
  std::optional<v1::RenderResponse> idle_notice = idle.Read();
  ASSERT_TRUE(idle_notice.has_value() && idle_notice->has_notice());
  EXPECT_EQ(idle_notice->notice().reason(), v1::SessionNotice::REASON_DRAINING);
  EXPECT_EQ(idle.Read(), std::nullopt);
  EXPECT_EQ(idle.Finish().error_code(), grpc::StatusCode::UNAVAILABLE);

  // The frame in flight still completes and is answered, then UNAVAILABLE.
  gate->Open();
  std::optional<v1::RenderResponse> frame = busy.Read();
  ASSERT_TRUE(frame.has_value() && frame->has_frame()) << frame->DebugString();
  EXPECT_EQ(frame->frame().frame_index(), 0u);
  EXPECT_EQ(busy.Read(), std::nullopt);
  grpc::Status status = busy.Finish();
  EXPECT_EQ(status.error_code(), grpc::StatusCode::UNAVAILABLE);
  EXPECT_THAT(status.error_message(), HasSubstr("shutting down"));
  shutdown.join();
}

TEST(LifecycleTest, ResumeWhileTheBrokenStreamsFrameIsStillRenderingWaitsForIt) {
  // The broken stream's frame is stuck in its first step. The resume is
  // answered only once that frame is dropped (at the next step boundary),
  // so the answer can say that frame 0 was not rendered; the re-sent frame
  // 0 then renders instead of failing with "still in flight".
  GatedServer gated = StartGated(/*gated_call=*/0);
  ASSERT_NE(gated.server, nullptr);
  StreamClient resumed(Connect(*gated.server));
  std::optional<v1::SessionOpened> again = ResumeWhileTheFrameIsHeld(gated, resumed);
  ASSERT_TRUE(again.has_value());
  EXPECT_TRUE(again->resumed());
  EXPECT_FALSE(again->has_last_frame_index());
  ASSERT_TRUE(resumed.Write(MakeFrame(0)));
  std::optional<v1::RenderResponse> frame = resumed.Read();
  ASSERT_TRUE(frame.has_value() && frame->has_frame()) << frame->DebugString();
  EXPECT_EQ(frame->frame().frame_index(), 0u);
  ASSERT_TRUE(resumed.Write(MakeFrame(1)));
  EXPECT_TRUE(resumed.Read()->has_frame());
}

TEST(LifecycleTest, ResumeAnswerCountsTheBrokenStreamsFrameThatCompletedAnyway) {
  // The broken stream's frame is held in its LAST step: no step boundary is
  // left to drop it at, so it completes after the takeover and its answer is
  // lost with the old stream. The resume answer must say so
  // (last_frame_index 0), so the client neither re-sends frame 0 (which
  // would be refused) nor believes the session is where it left it.
  GatedServer gated = StartGated(/*gated_call=*/kSteps - 1);
  ASSERT_NE(gated.server, nullptr);
  StreamClient resumed(Connect(*gated.server));
  std::optional<v1::SessionOpened> again = ResumeWhileTheFrameIsHeld(gated, resumed);
  ASSERT_TRUE(again.has_value());
  EXPECT_TRUE(again->resumed());
  ASSERT_TRUE(again->has_last_frame_index());
  EXPECT_EQ(again->last_frame_index(), 0u);
  // Frame 0 was rendered: a re-send is refused, naming the field; frame 1
  // continues the chain.
  ASSERT_TRUE(resumed.Write(MakeFrame(0)));
  std::optional<v1::RenderResponse> refused = resumed.Read();
  ASSERT_TRUE(refused.has_value() && refused->has_frame_error()) << refused->DebugString();
  EXPECT_EQ(refused->frame_error().code(), grpc::StatusCode::FAILED_PRECONDITION);
  EXPECT_THAT(refused->frame_error().message(), HasSubstr("frame_index"));
  ASSERT_TRUE(resumed.Write(MakeFrame(1)));
  std::optional<v1::RenderResponse> frame = resumed.Read();
  ASSERT_TRUE(frame.has_value() && frame->has_frame()) << frame->DebugString();
  EXPECT_EQ(frame->frame().frame_index(), 1u);
}

TEST(LifecycleTest, IdleSessionExpiresWithANoticeAndResumeSaysExpired) {
  fd::testing::FakeClock clock;
  ServerOptions options;
  options.config = TestConfig();
  options.config.idle_timeout = absl::Minutes(5);
  options.environments.emplace_back(kEmbeddedEnvironmentName, TinyEnvironment());
  options.clock = &clock;
  auto server = StartOrNull(std::move(options));
  ASSERT_NE(server, nullptr);
  StreamClient stream(Connect(*server));
  v1::SessionOpened opened = OpenOn(stream, MakeOpen());

  clock.Advance(absl::Minutes(6));
  server->ExpireIdleSessionsNow();
  std::optional<v1::RenderResponse> notice = stream.Read();
  ASSERT_TRUE(notice.has_value() && notice->has_notice());
  EXPECT_EQ(notice->notice().reason(), v1::SessionNotice::REASON_EXPIRED);
  EXPECT_EQ(stream.Finish().error_code(), grpc::StatusCode::NOT_FOUND);

  StreamClient again(Connect(*server));
  again.Write(MakeResume(opened.session_id(), opened.resume_token()));
  std::optional<v1::RenderResponse> why = again.Read();
  ASSERT_TRUE(why.has_value() && why->has_notice());
  EXPECT_EQ(why->notice().reason(), v1::SessionNotice::REASON_EXPIRED);
  EXPECT_EQ(again.Finish().error_code(), grpc::StatusCode::NOT_FOUND);
}

class RepositoryTest : public ::testing::Test {
 protected:
  void SetUp() override {
    repo_ = fs::path(::testing::TempDir()) /
            ::testing::UnitTest::GetInstance()->current_test_info()->name();
    fs::remove_all(repo_);
    fs::create_directories(repo_);
  }
  void WriteEnvironment(const std::string& name) {
    ASSERT_TRUE(session::WriteRandomTinyEnvironment((repo_ / name).string()).ok());
  }
  std::unique_ptr<FrameDiffuserServer> StartOnRepo() {
    ServerOptions options;
    options.config = TestConfig();
    options.config.model_repository = repo_.string();
    options.wait_for_environments = true;
    return StartOrNull(std::move(options));
  }
  std::vector<std::string> Names(FrameDiffuserServer& server, session::Readiness readiness) {
    std::vector<std::string> names;
    for (const session::EnvironmentInfo& info : server.registry().List()) {
      if (info.readiness == readiness) names.push_back(info.name);
    }
    return names;
  }
  fs::path repo_;
};

TEST_F(RepositoryTest, LoadsEveryFolderAndIgnoresOthers) {
  WriteEnvironment("street");
  WriteEnvironment("room");
  fs::create_directories(repo_ / "not_an_environment");
  auto server = StartOnRepo();
  ASSERT_NE(server, nullptr);
  EXPECT_THAT(Names(*server, session::Readiness::kReady), ::testing::ElementsAre("room", "street"));
  EXPECT_THAT(
      server->metrics().Scrape(),
      HasSubstr("framediffuser_model_loads_total{environment=\"street\",outcome=\"ok\"} 1"));
}

TEST_F(RepositoryTest, AddRemoveAndReloadAtRunTimeLeaveOtherSessionsAlone) {
  WriteEnvironment("street");
  WriteEnvironment("room");
  auto server = StartOnRepo();
  ASSERT_NE(server, nullptr);

  StreamClient street(Connect(*server));
  OpenOn(street, MakeOpen("street"));
  StreamClient room(Connect(*server));
  OpenOn(room, MakeOpen("room"));
  ASSERT_TRUE(street.Write(MakeFrame(0)));
  ASSERT_TRUE(street.Read()->has_frame());

  // Add "forest", remove "room".
  WriteEnvironment("forest");
  fs::remove_all(repo_ / "room");
  ASSERT_TRUE(server->Rescan().ok());
  server->registry().AwaitLoads();
  EXPECT_THAT(Names(*server, session::Readiness::kReady),
              ::testing::ElementsAre("forest", "street"));

  // The removed environment's session was evicted and told so.
  std::optional<v1::RenderResponse> notice = room.Read();
  ASSERT_TRUE(notice.has_value() && notice->has_notice());
  EXPECT_EQ(notice->notice().reason(), v1::SessionNotice::REASON_EVICTED);
  EXPECT_THAT(notice->notice().message(), HasSubstr("removed"));
  EXPECT_EQ(room.Finish().error_code(), grpc::StatusCode::NOT_FOUND);

  // Reload "street" (its environment.json changed: 12 default steps) while
  // its session is open: the session carries on across the swap.
  {
    std::ofstream json(repo_ / "street" / "environment.json", std::ios::trunc);
    json << R"({"name": "street", "description": "reloaded", "width": 128, "height": 128,
               "steps": 6, "sky_mode": "previous_output"})";
  }
  ASSERT_TRUE(server->Rescan().ok());
  server->registry().AwaitLoads();
  absl::StatusOr<session::EnvironmentHandle> reloaded = server->registry().Acquire("street");
  ASSERT_TRUE(reloaded.ok());
  EXPECT_EQ(reloaded->info.description, "reloaded");
  EXPECT_EQ(reloaded->info.default_steps, 6u);
  for (uint64_t i = 1; i < 3; ++i) {
    ASSERT_TRUE(street.Write(MakeFrame(i)));
    std::optional<v1::RenderResponse> frame = street.Read();
    ASSERT_TRUE(frame.has_value() && frame->has_frame()) << frame->DebugString();
  }
  // And the new environment serves.
  StreamClient forest(Connect(*server));
  OpenOn(forest, MakeOpen("forest"));
  ASSERT_TRUE(forest.Write(MakeFrame(0)));
  EXPECT_TRUE(forest.Read()->has_frame());
}

TEST_F(RepositoryTest, AFailedLoadIsReportedAndRetriedOnRescan) {
  fs::create_directories(repo_ / "broken");
  std::ofstream(repo_ / "broken" / "environment.json") << "{}";
  auto server = StartOnRepo();
  ASSERT_NE(server, nullptr);
  std::vector<session::EnvironmentInfo> infos = server->registry().List();
  ASSERT_EQ(infos.size(), 1u);
  EXPECT_EQ(infos[0].readiness, session::Readiness::kFailed);
  EXPECT_THAT(infos[0].readiness_detail, HasSubstr("unet"));

  // Fixed on disk: the next rescan loads it.
  ASSERT_TRUE(session::WriteRandomTinyEnvironment((repo_ / "broken").string()).ok());
  ASSERT_TRUE(server->Rescan().ok());
  server->registry().AwaitLoads();
  EXPECT_THAT(Names(*server, session::Readiness::kReady), ::testing::ElementsAre("broken"));
}

TEST_F(RepositoryTest, MissingRepositoryIsAnError) {
  ServerOptions options;
  options.config = TestConfig();
  options.config.model_repository = (repo_ / "nope").string();
  absl::StatusOr<std::unique_ptr<FrameDiffuserServer>> server =
      FrameDiffuserServer::Start(std::move(options));
  ASSERT_FALSE(server.ok());
  EXPECT_EQ(server.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(server.status().message(), HasSubstr("--model_repository"));
}

}  // namespace
}  // namespace fd::server

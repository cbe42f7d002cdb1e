// Server lifecycle: graceful drain with frames in flight, idle expiry and
// eviction notices, and the model repository (load, add, remove, reload at
// run time without disturbing other sessions; reloads and corrupt folders
// while sessions stream).
#include <grpcpp/grpcpp.h>

#include <chrono>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/synchronization/mutex.h"
#include "absl/synchronization/notification.h"
#include "base/image_buffer.h"
#include "gmock/gmock.h"
#include "grpc/health/v1/health.grpc.pb.h"
#include "gtest/gtest.h"
#include "model/pipeline/environment.h"
#include "session/session.h"
#include "session/session_settings.h"
#include "session/session_state.h"
#include "session/session_store.h"
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

// Holds every denoising step of the FIRST pipeline built for one repository
// folder (the model loaded at start-up; a reload builds a second pipeline,
// which runs freely) until Release(), and counts the steps it held. A frame
// whose step is held is provably in flight on that first model, however
// long the test takes meanwhile: no race decides what it renders on.
class FirstModelStepHold {
 public:
  explicit FirstModelStepHold(std::string folder_name) : folder_name_(std::move(folder_name)) {}

  // Whether the pipeline being built for `env` is the one to hold.
  bool Claim(const model::Environment& env) {
    absl::MutexLock lock(&mu_);
    if (claimed_ || fs::path(env.dir).filename().string() != folder_name_) return false;
    claimed_ = true;
    return true;
  }
  // Runs on a batcher worker before each step of the held pipeline.
  void Hold() {
    absl::MutexLock lock(&mu_);
    ++held_;
    mu_.Await(absl::Condition(&released_));
  }
  // Blocks until `n` steps were held (each is one worker's batch).
  void AwaitHeld(int n) {
    absl::MutexLock lock(&mu_);
    auto enough = [this, n]() {
      mu_.AssertReaderHeld();
      return held_ >= n;
    };
    mu_.Await(absl::Condition(&enough));
  }
  void Release() {
    absl::MutexLock lock(&mu_);
    released_ = true;
  }

 private:
  const std::string folder_name_;
  absl::Mutex mu_;
  bool claimed_ ABSL_GUARDED_BY(mu_) = false;
  bool released_ ABSL_GUARDED_BY(mu_) = false;
  int held_ ABSL_GUARDED_BY(mu_) = 0;
};

// Releases a hold when it goes out of scope: declared after the server, it
// lets held steps go before the server shuts down even when a failed
// ASSERT ends the test early (the shutdown waits for those frames).
struct ReleaseOnExit {
  ~ReleaseOnExit() { hold->Release(); }
  std::shared_ptr<FirstModelStepHold> hold;
};

// The finished repository loads per environment (ServerOptions::
// on_load_finished), so that a test can wait until a reload swapped the
// model in without waiting for the old model's frames (AwaitLoads does).
class LoadLog {
 public:
  void Record(const std::string& name, const absl::Status& status) {
    absl::MutexLock lock(&mu_);
    loads_[name].push_back(status);
  }
  // Blocks until `name` finished `n` loads (first load included); returns
  // the last one's status.
  absl::Status AwaitLoads(const std::string& name, size_t n) {
    absl::MutexLock lock(&mu_);
    auto enough = [this, &name, n]() {
      mu_.AssertReaderHeld();
      auto it = loads_.find(name);
      return it != loads_.end() && it->second.size() >= n;
    };
    mu_.Await(absl::Condition(&enough));
    return loads_[name].back();
  }

 private:
  absl::Mutex mu_;
  std::map<std::string, std::vector<absl::Status>> loads_ ABSL_GUARDED_BY(mu_);
};

// The pipelines of the bitwise tests: the real one with batch_invariant (a
// custom factory replaces the server's own pipeline, which would take it
// from config.batch_invariant), wrapped so that `hold` (if any) can hold
// its folder's first model.
session::PipelineFactory BatchInvariantPipelines(std::shared_ptr<FirstModelStepHold> hold) {
  return [hold](std::shared_ptr<const model::Environment> env)
             -> std::unique_ptr<session::FramePipelineInterface> {
    model::FramePipelineOptions options;
    options.batch_invariant = true;
    auto pipeline = std::make_unique<fd::testing::ScriptedFramePipeline>(
        std::make_shared<session::ModelFramePipeline>(env, options));
    if (hold != nullptr && hold->Claim(*env)) {
      pipeline->before_step = [hold](int, size_t) { hold->Hold(); };
    }
    return pipeline;
  };
}

// The bytes of the next answer, which must be rendered frame `index` ("" and
// a failure otherwise).
std::string ReadFrame(StreamClient& stream, uint64_t index) {
  std::optional<v1::RenderResponse> answer = stream.Read();
  if (!answer.has_value() || !answer->has_frame()) {
    ADD_FAILURE() << "expected frame " << index << ", got "
                  << (answer.has_value() ? answer->DebugString() : "end of stream");
    return "";
  }
  EXPECT_EQ(answer->frame().frame_index(), index);
  return answer->frame().image().data();
}

// Sends frame `index` and returns its bytes.
std::string RenderFrame(StreamClient& stream, uint64_t index) {
  EXPECT_TRUE(stream.Write(MakeFrame(index)));
  return ReadFrame(stream, index);
}

// Renders frames first .. first + count - 1 in lock step (write, read).
std::vector<std::string> RenderFrames(StreamClient& stream, uint64_t first, uint64_t count) {
  std::vector<std::string> frames;
  for (uint64_t i = first; i < first + count; ++i) frames.push_back(RenderFrame(stream, i));
  return frames;
}

// Bitwise equality of two rendered frames, without printing kilobytes of
// pixels when they differ.
::testing::AssertionResult SameFrame(const std::string& actual, const std::string& expected) {
  if (actual.empty() || expected.empty()) {
    return ::testing::AssertionFailure() << "a frame is missing";
  }
  if (actual == expected) return ::testing::AssertionSuccess();
  size_t first = 0;
  while (first < actual.size() && first < expected.size() && actual[first] == expected[first]) {
    ++first;
  }
  return ::testing::AssertionFailure()
         << "frames differ (" << actual.size() << " vs " << expected.size()
         << " bytes, first at byte " << first << ")";
}

// A uint8 RGB image of the test size holding `bytes`.
ImageBuffer Rgb(const std::string& bytes) {
  ImageBuffer image(kSize, kSize, 3, PixelType::kUint8);
  EXPECT_EQ(bytes.size(), image.size_bytes());
  if (bytes.size() == image.size_bytes())
    std::memcpy(image.mutable_data(), bytes.data(), bytes.size());
  return image;
}

// Every environment as ListEnvironments reports it on the wire, by name.
std::map<std::string, v1::Environment> WireEnvironments(FrameDiffuserServer& server) {
  auto stub = v1::FrameDiffuser::NewStub(Connect(server));
  grpc::ClientContext context;
  v1::ListEnvironmentsResponse response;
  EXPECT_TRUE(stub->ListEnvironments(&context, {}, &response).ok());
  std::map<std::string, v1::Environment> environments;
  for (const v1::Environment& environment : response.environments()) {
    environments[environment.name()] = environment;
  }
  return environments;
}

// The health status of `service` (or minus the call's error code).
int Health(FrameDiffuserServer& server, const std::string& service) {
  auto health = grpc::health::v1::Health::NewStub(Connect(server));
  grpc::ClientContext context;
  grpc::health::v1::HealthCheckRequest request;
  request.set_service(service);
  grpc::health::v1::HealthCheckResponse response;
  grpc::Status status = health->Check(&context, request, &response);
  return status.ok() ? static_cast<int>(response.status()) : -static_cast<int>(status.error_code());
}

// Frames a solo session (seed 7, MakeFrame inputs) renders on two versions
// of the random tiny environment, as references.
struct References {
  std::vector<std::string> old_weights;  // frames 0..3, all on the old weights
  std::vector<std::string> new_weights;  // frames 0..1, all on the new weights
  // Frames 1..2 on the new weights after frame 0 on the old ones: what an
  // open session renders once the model was swapped after its frame 0.
  // Index 0 is unused.
  std::vector<std::string> old_then_new;
};

class RepositoryTest : public ::testing::Test {
 protected:
  static constexpr uint64_t kOldSeed = session::kRandomEnvironmentSeed;
  static constexpr uint64_t kNewSeed = session::kRandomEnvironmentSeed + 1;

  void SetUp() override {
    repo_ = fs::path(::testing::TempDir()) /
            ::testing::UnitTest::GetInstance()->current_test_info()->name();
    fs::remove_all(repo_);
    fs::create_directories(repo_);
  }
  void TearDown() override {
    std::error_code ec;
    fs::remove_all(ReferenceRepo(), ec);
  }
  void WriteEnvironment(const std::string& name, uint64_t seed = session::kRandomEnvironmentSeed) {
    ASSERT_TRUE(session::WriteRandomTinyEnvironment((repo_ / name).string(), seed).ok());
  }
  // The registry notices a changed folder by its files' names, sizes and
  // modification times. A rewrite with files of the same sizes can land in
  // the same file-system timestamp tick as the first write, so move every
  // file's time one second on: the folder then surely looks changed.
  void MarkChanged(const std::string& name) {
    for (const fs::directory_entry& entry : fs::recursive_directory_iterator(repo_ / name)) {
      if (!entry.is_regular_file()) continue;
      fs::last_write_time(entry.path(), entry.last_write_time() + std::chrono::seconds(1));
    }
  }
  std::unique_ptr<FrameDiffuserServer> StartOnRepo() {
    ServerOptions options;
    options.config = TestConfig();
    options.config.model_repository = repo_.string();
    options.wait_for_environments = true;
    return StartOrNull(std::move(options));
  }
  // A server for the bitwise checks: frames independent of their batch mates
  // (batch_invariant) and two batcher workers of one LibTorch thread each
  // (a frame's arithmetic then does not depend on the machine's cores, and
  // two frames of two sessions can be in flight at once, one per worker).
  ServerOptions BitwiseOptions(const fs::path& repo, std::shared_ptr<FirstModelStepHold> hold) {
    ServerOptions options;
    options.config = TestConfig();
    options.config.model_repository = repo.string();
    options.config.batch_invariant = true;
    options.config.scheduler_workers = 2;
    options.config.threads = 1;
    options.pipeline_factory = BatchInvariantPipelines(std::move(hold));
    options.on_load_finished = [loads = loads_](const std::string& name,
                                                const absl::Status& status) {
      loads->Record(name, status);
    };
    options.wait_for_environments = true;
    return options;
  }
  fs::path ReferenceRepo() const { return fs::path(repo_.string() + "_reference"); }

  // Renders the references on a server of their own (the same options, no
  // hold, no reload): "old" and "new" are the two versions.
  References RenderReferences() {
    References refs;
    const fs::path reference_repo = ReferenceRepo();
    fs::remove_all(reference_repo);
    EXPECT_TRUE(
        session::WriteRandomTinyEnvironment((reference_repo / "old").string(), kOldSeed).ok());
    EXPECT_TRUE(
        session::WriteRandomTinyEnvironment((reference_repo / "new").string(), kNewSeed).ok());
    std::unique_ptr<FrameDiffuserServer> reference =
        StartOrNull(BitwiseOptions(reference_repo, nullptr));
    if (reference == nullptr) return refs;
    {
      StreamClient solo(Connect(*reference));
      OpenOn(solo, MakeOpen("old"));
      refs.old_weights = RenderFrames(solo, 0, 4);
    }
    StreamClient solo(Connect(*reference));
    const v1::SessionOpened opened = OpenOn(solo, MakeOpen("new"));
    refs.new_weights = RenderFrames(solo, 0, 2);

    // A session's state is its last output, that frame's basecolor and a
    // frame counter (session_state.h). The state an open session has after
    // frame 0 rendered on the old weights, restored on the new ones, renders
    // what that session should render after the swap.
    absl::StatusOr<std::shared_ptr<session::Session>> on_new =
        reference->store().Lookup(opened.session_id());
    EXPECT_TRUE(on_new.ok()) << on_new.status();
    if (!on_new.ok() || refs.old_weights.empty()) return refs;
    absl::StatusOr<session::SessionState> after_old_frame_0 = session::SessionState::Restore(
        (*on_new)->settings(), session::StartMode::kGBufferOnly, /*frame_counter=*/1,
        /*last_frame_index=*/0, Rgb(refs.old_weights[0]),
        Rgb(MakeFrame(0).frame().gbuffer().basecolor().data()));
    EXPECT_TRUE(after_old_frame_0.ok()) << after_old_frame_0.status();
    if (!after_old_frame_0.ok()) return refs;
    absl::StatusOr<session::CreatedSession> created =
        reference->store().Create("", *std::move(after_old_frame_0));
    EXPECT_TRUE(created.ok()) << created.status();
    if (!created.ok()) return refs;
    StreamClient continued(Connect(*reference));
    const v1::SessionOpened resumed =
        OpenOn(continued, MakeResume(created->session->id(), created->resume_secret));
    EXPECT_TRUE(resumed.resumed());
    refs.old_then_new = RenderFrames(continued, 1, 2);
    refs.old_then_new.insert(refs.old_then_new.begin(), "");
    return refs;
  }

  std::vector<std::string> Names(FrameDiffuserServer& server, session::Readiness readiness) {
    std::vector<std::string> names;
    for (const session::EnvironmentInfo& info : server.registry().List()) {
      if (info.readiness == readiness) names.push_back(info.name);
    }
    return names;
  }
  std::optional<session::EnvironmentInfo> Info(FrameDiffuserServer& server,
                                               const std::string& name) {
    for (const session::EnvironmentInfo& info : server.registry().List()) {
      if (info.name == name) return info;
    }
    return std::nullopt;
  }
  fs::path repo_;
  std::shared_ptr<LoadLog> loads_ = std::make_shared<LoadLog>();
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

// An environment.json with "previous_latent": "reuse" reaches the batcher:
// its sessions keep each frame's latent (and frame 1 on differs from the
// encoded chain), while an environment without it keeps none.
TEST_F(RepositoryTest, PreviousLatentReuseIsTheEnvironmentsChoice) {
  WriteEnvironment("encoded");
  WriteEnvironment("reused");
  {
    std::ifstream in(repo_ / "reused" / "environment.json");
    std::string json((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    ASSERT_EQ(json.front(), '{');
    json.insert(1, R"("previous_latent": "reuse", )");
    std::ofstream(repo_ / "reused" / "environment.json", std::ios::trunc) << json;
  }
  std::unique_ptr<FrameDiffuserServer> server = StartOrNull(BitwiseOptions(repo_, nullptr));
  ASSERT_NE(server, nullptr);
  std::map<std::string, std::vector<std::string>> frames;
  for (const std::string name : {"encoded", "reused"}) {
    StreamClient stream(Connect(*server));
    const v1::SessionOpened opened = OpenOn(stream, MakeOpen(name));
    frames[name] = RenderFrames(stream, 0, 3);
    absl::StatusOr<std::shared_ptr<session::Session>> session =
        server->store().Lookup(opened.session_id());
    ASSERT_TRUE(session.ok()) << session.status();
    const session::LatentBuffer latent = (*session)->StateSnapshot().previous_latent();
    if (name == "encoded") {
      EXPECT_TRUE(latent.empty());
    } else {
      ASSERT_FALSE(latent.empty());
      EXPECT_EQ(latent.channels, 4u);
      EXPECT_EQ(latent.values->size(),
                static_cast<size_t>(latent.channels) * latent.height * latent.width);
    }
  }
  ASSERT_EQ(frames["encoded"].size(), 3u);
  ASSERT_EQ(frames["reused"].size(), 3u);
  EXPECT_EQ(frames["encoded"][0], frames["reused"][0]);  // G-buffer-only start: no latent yet
  EXPECT_NE(frames["encoded"][1], frames["reused"][1]);
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

// A reload (what SIGHUP does: FrameDiffuserServer::Rescan) of an environment
// while its sessions stream. The swap is per frame, not per session
// (environment_registry.h): a frame already handed to the old model's
// batcher finishes on the old weights; every frame handed over after the
// swap renders on the new ones, for new sessions AND for the sessions that
// were open, which carry on from their last (old-weight) output. A session
// hands the batcher one frame at a time, so frames a client sent but whose
// predecessor was still rendering are handed over, and render, after the
// swap.
//
// Nothing here depends on timing: the old model's steps are held
// (FirstModelStepHold) until the new model serves (the load log says the
// reload finished), so frames 0 of `a` and `b` are provably on the old
// model and everything after provably on the new one.
TEST_F(RepositoryTest, ReloadUnderLoadFinishesFramesInFlightOnOldWeightsThenServesNewOnes) {
  const References refs = RenderReferences();
  ASSERT_EQ(refs.old_weights.size(), 4u);
  ASSERT_EQ(refs.new_weights.size(), 2u);
  ASSERT_EQ(refs.old_then_new.size(), 3u);
  // The two versions render differently (else this test would prove nothing).
  ASSERT_FALSE(SameFrame(refs.new_weights[0], refs.old_weights[0]));
  ASSERT_FALSE(SameFrame(refs.old_then_new[1], refs.old_weights[1]));

  WriteEnvironment("street", kOldSeed);
  auto hold = std::make_shared<FirstModelStepHold>("street");
  std::unique_ptr<FrameDiffuserServer> server = StartOrNull(BitwiseOptions(repo_, hold));
  ASSERT_NE(server, nullptr);
  const ReleaseOnExit release{hold};

  StreamClient a(Connect(*server));
  OpenOn(a, MakeOpen("street"));
  StreamClient b(Connect(*server));
  OpenOn(b, MakeOpen("street"));
  StreamClient idle(Connect(*server));  // open across the swap, no frame before it
  OpenOn(idle, MakeOpen("street"));
  ASSERT_TRUE(a.Write(MakeFrame(0)));
  hold->AwaitHeld(1);
  // b's frame only now: one worker is stuck in a's step, so the other takes
  // b's frame alone (sent together, both could share one batch and one held
  // step, and AwaitHeld(2) would never return).
  ASSERT_TRUE(b.Write(MakeFrame(0)));
  hold->AwaitHeld(2);
  // Sent before the swap, but they wait in a's stream behind frame 0.
  ASSERT_TRUE(a.Write(MakeFrame(1)));
  ASSERT_TRUE(a.Write(MakeFrame(2)));

  WriteEnvironment("street", kNewSeed);
  MarkChanged("street");
  ASSERT_TRUE(server->Rescan().ok());
  // The first load and the reload: the new model now takes new frames, while
  // the old one's batcher is still held with its two frames (AwaitLoads would
  // wait for those, so it cannot be used here).
  ASSERT_TRUE(loads_->AwaitLoads("street", 2).ok());
  EXPECT_THAT(Names(*server, session::Readiness::kReady), ::testing::ElementsAre("street"));
  EXPECT_THAT(WireEnvironments(*server)["street"].description(),
              HasSubstr(absl::StrCat("seed ", kNewSeed)));
  StreamClient fresh(Connect(*server));  // opened after the swap
  OpenOn(fresh, MakeOpen("street"));
  hold->Release();

  // In flight at the swap: the old weights.
  EXPECT_TRUE(SameFrame(ReadFrame(a, 0), refs.old_weights[0]));
  EXPECT_TRUE(SameFrame(ReadFrame(b, 0), refs.old_weights[0]));
  // Handed over after it: the new weights, from the old frame 0's state.
  EXPECT_TRUE(SameFrame(ReadFrame(a, 1), refs.old_then_new[1]));
  EXPECT_TRUE(SameFrame(ReadFrame(a, 2), refs.old_then_new[2]));
  ASSERT_TRUE(b.Write(MakeFrame(1)));
  EXPECT_TRUE(SameFrame(ReadFrame(b, 1), refs.old_then_new[1]));
  // An open session's first frame, and a new session's: all new weights.
  std::vector<std::string> idle_frames = RenderFrames(idle, 0, 2);
  std::vector<std::string> fresh_frames = RenderFrames(fresh, 0, 2);
  ASSERT_EQ(idle_frames.size(), 2u);
  ASSERT_EQ(fresh_frames.size(), 2u);
  for (size_t i = 0; i < 2; ++i) {
    EXPECT_TRUE(SameFrame(idle_frames[i], refs.new_weights[i])) << "frame " << i;
    EXPECT_TRUE(SameFrame(fresh_frames[i], refs.new_weights[i])) << "frame " << i;
  }
  // The old model's batcher drained its two frames and is gone.
  server->registry().AwaitLoads();
  EXPECT_THAT(
      server->metrics().Scrape(),
      HasSubstr("framediffuser_model_loads_total{environment=\"street\",outcome=\"ok\"} 2"));
}

// Copies repository folder `from` to `to` (a new folder).
void CopyFolder(const fs::path& from, const fs::path& to) {
  fs::copy(from, to, fs::copy_options::recursive);
}

// Overwrites `length` bytes at `offset` of `path` with '#' (the size stays).
void Scribble(const fs::path& path, std::streamoff offset, size_t length) {
  std::fstream file(path, std::ios::in | std::ios::out | std::ios::binary);
  file.seekp(offset);
  const std::string garbage(length, '#');
  file.write(garbage.data(), static_cast<std::streamsize>(garbage.size()));
  ASSERT_TRUE(file.good()) << path;
}

// Corrupt checkpoint folders appearing in the repository (a rescan) while
// another environment's session streams: each is FAILED with the file named,
// on the wire too, and nothing else notices. The street session's frame 0 is
// held on its model for the whole rescan (no race decides whether the rescan
// overlaps it); its frames are compared with a server that never rescans.
TEST_F(RepositoryTest, CorruptFoldersAppearingUnderLoadFailNamingTheFileAndHarmNothingElse) {
  const References refs = RenderReferences();
  ASSERT_EQ(refs.old_weights.size(), 4u);
  WriteEnvironment("street");
  WriteEnvironment("room");  // the same weights as street (and "old")
  auto hold = std::make_shared<FirstModelStepHold>("street");
  std::unique_ptr<FrameDiffuserServer> server = StartOrNull(BitwiseOptions(repo_, hold));
  ASSERT_NE(server, nullptr);
  const ReleaseOnExit release{hold};

  StreamClient street(Connect(*server));
  OpenOn(street, MakeOpen("street"));
  StreamClient room(Connect(*server));
  OpenOn(room, MakeOpen("room"));
  ASSERT_TRUE(room.Write(MakeFrame(0)));
  ASSERT_TRUE(street.Write(MakeFrame(0)));
  hold->AwaitHeld(1);

  const std::string unet = "unet/diffusion_pytorch_model.safetensors";
  CopyFolder(repo_ / "street", repo_ / "truncated_unet");
  const fs::path truncated = repo_ / "truncated_unet" / unet;
  fs::resize_file(truncated, fs::file_size(truncated) / 2);
  CopyFolder(repo_ / "street", repo_ / "garbage_header");
  // The 8-byte header length stays; the JSON header after it is garbage.
  Scribble(repo_ / "garbage_header" / unet, 8, 16);
  CopyFolder(repo_ / "street", repo_ / "invalid_config");
  std::ofstream(repo_ / "invalid_config" / "unet" / "config.json", std::ios::trunc)
      << "{\"in_channels\": 8,";
  ASSERT_TRUE(server->Rescan().ok());
  // The broken folders fail to load, so no model is swapped and nothing
  // waits for the held frame.
  server->registry().AwaitLoads();

  EXPECT_THAT(Names(*server, session::Readiness::kReady), ::testing::ElementsAre("room", "street"));
  // Per broken folder: the file its detail must name, and what is wrong.
  const std::map<std::string, std::pair<fs::path, std::string>> why = {
      {"truncated_unet", {repo_ / "truncated_unet" / unet, "(file truncated?)"}},
      {"garbage_header", {repo_ / "garbage_header" / unet, "header is not valid JSON"}},
      {"invalid_config", {repo_ / "invalid_config" / "unet" / "config.json", "not valid JSON"}},
  };
  std::map<std::string, v1::Environment> wire = WireEnvironments(*server);
  for (const auto& [name, file_and_reason] : why) {
    const auto& [file, reason] = file_and_reason;
    std::optional<session::EnvironmentInfo> info = Info(*server, name);
    ASSERT_TRUE(info.has_value()) << name;
    EXPECT_EQ(info->readiness, session::Readiness::kFailed) << name;
    EXPECT_THAT(info->readiness_detail, HasSubstr(absl::StrCat("'", file.string(), "'"))) << name;
    EXPECT_THAT(info->readiness_detail, HasSubstr(reason)) << name;
    EXPECT_EQ(wire[name].readiness(), v1::READINESS_FAILED) << name;
    EXPECT_EQ(wire[name].readiness_detail(), info->readiness_detail) << name;
    EXPECT_EQ(Health(*server, EnvironmentHealthName(name)),
              grpc::health::v1::HealthCheckResponse::NOT_SERVING)
        << name;
    EXPECT_THAT(server->metrics().Scrape(),
                HasSubstr(absl::StrCat("framediffuser_model_loads_total{environment=\"", name,
                                       "\",outcome=\"error\"} 1")));
  }
  for (const char* name : {"street", "room"}) {
    EXPECT_EQ(wire[name].readiness(), v1::READINESS_READY) << name;
    EXPECT_EQ(wire[name].readiness_detail(), "") << name;
    EXPECT_EQ(Health(*server, EnvironmentHealthName(name)),
              grpc::health::v1::HealthCheckResponse::SERVING)
        << name;
  }
  EXPECT_EQ(Health(*server, kServiceName), grpc::health::v1::HealthCheckResponse::SERVING);
  // Opening one of them is refused with the same reason.
  StreamClient refused(Connect(*server));
  ASSERT_TRUE(refused.Write(MakeOpen("garbage_header")));
  EXPECT_EQ(refused.Read(), std::nullopt);
  grpc::Status status = refused.Finish();
  EXPECT_EQ(status.error_code(), grpc::StatusCode::UNAVAILABLE);
  EXPECT_THAT(status.error_message(), HasSubstr(why.at("garbage_header").first.string()));
  EXPECT_THAT(status.error_message(), HasSubstr(why.at("garbage_header").second));

  // The sessions carry on, bitwise as without the rescan.
  hold->Release();
  std::vector<std::string> street_frames = {ReadFrame(street, 0)};
  for (const std::string& frame : RenderFrames(street, 1, 3)) street_frames.push_back(frame);
  std::vector<std::string> room_frames = {ReadFrame(room, 0)};
  for (const std::string& frame : RenderFrames(room, 1, 3)) room_frames.push_back(frame);
  ASSERT_EQ(street_frames.size(), 4u);
  ASSERT_EQ(room_frames.size(), 4u);
  for (size_t i = 0; i < 4; ++i) {
    EXPECT_TRUE(SameFrame(street_frames[i], refs.old_weights[i])) << "street frame " << i;
    EXPECT_TRUE(SameFrame(room_frames[i], refs.old_weights[i])) << "room frame " << i;
  }
}

// A served environment whose files turn corrupt: the reload fails, the old
// model keeps serving (READY, the same model, the same frames) and the
// failure is reported (load result, metrics); once fixed on disk, the next
// rescan swaps the new model in.
TEST_F(RepositoryTest, AReloadOfCorruptFilesKeepsTheOldModelServingAndIsReported) {
  const References refs = RenderReferences();
  ASSERT_EQ(refs.old_weights.size(), 4u);
  ASSERT_EQ(refs.new_weights.size(), 2u);
  WriteEnvironment("street", kOldSeed);
  std::unique_ptr<FrameDiffuserServer> server = StartOrNull(BitwiseOptions(repo_, nullptr));
  ASSERT_NE(server, nullptr);
  absl::StatusOr<session::EnvironmentHandle> before = server->registry().Acquire("street");
  ASSERT_TRUE(before.ok());

  StreamClient open(Connect(*server));
  OpenOn(open, MakeOpen("street"));
  EXPECT_TRUE(SameFrame(RenderFrame(open, 0), refs.old_weights[0]));

  const fs::path unet = repo_ / "street" / "unet" / "diffusion_pytorch_model.safetensors";
  fs::resize_file(unet, fs::file_size(unet) / 2);
  MarkChanged("street");
  ASSERT_TRUE(server->Rescan().ok());
  server->registry().AwaitLoads();

  absl::Status reload = loads_->AwaitLoads("street", 2);
  EXPECT_FALSE(reload.ok());
  EXPECT_THAT(reload.message(), HasSubstr(unet.string()));
  EXPECT_THAT(
      server->metrics().Scrape(),
      HasSubstr("framediffuser_model_loads_total{environment=\"street\",outcome=\"error\"} 1"));
  // READY as before (the wire API keeps readiness_detail for what is not
  // READY), with the model loaded first.
  std::optional<session::EnvironmentInfo> info = Info(*server, "street");
  ASSERT_TRUE(info.has_value());
  EXPECT_EQ(info->readiness, session::Readiness::kReady);
  EXPECT_EQ(info->readiness_detail, "");
  absl::StatusOr<session::EnvironmentHandle> after = server->registry().Acquire("street");
  ASSERT_TRUE(after.ok());
  EXPECT_EQ(after->model, before->model);
  EXPECT_EQ(Health(*server, EnvironmentHealthName("street")),
            grpc::health::v1::HealthCheckResponse::SERVING);
  // The open session and a new one render on the old model.
  EXPECT_TRUE(SameFrame(RenderFrame(open, 1), refs.old_weights[1]));
  StreamClient opened_after(Connect(*server));
  OpenOn(opened_after, MakeOpen("street"));
  std::vector<std::string> frames = RenderFrames(opened_after, 0, 2);
  ASSERT_EQ(frames.size(), 2u);
  EXPECT_TRUE(SameFrame(frames[0], refs.old_weights[0]));
  EXPECT_TRUE(SameFrame(frames[1], refs.old_weights[1]));

  // Fixed on disk (with other weights): the next rescan reloads it.
  WriteEnvironment("street", kNewSeed);
  MarkChanged("street");
  ASSERT_TRUE(server->Rescan().ok());
  server->registry().AwaitLoads();
  EXPECT_TRUE(loads_->AwaitLoads("street", 3).ok());
  StreamClient on_new(Connect(*server));
  OpenOn(on_new, MakeOpen("street"));
  frames = RenderFrames(on_new, 0, 2);
  ASSERT_EQ(frames.size(), 2u);
  EXPECT_TRUE(SameFrame(frames[0], refs.new_weights[0]));
  EXPECT_TRUE(SameFrame(frames[1], refs.new_weights[1]));
}

}  // namespace
}  // namespace fd::server

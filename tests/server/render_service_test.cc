// The render service in-process on port 0 with the tiny environment: open,
// stream frames in order, close; resume after a disconnect (continuing the
// same chain); two environments at once; ListEnvironments, health and
// metrics.
#include <grpcpp/grpcpp.h>

#include <chrono>
#include <fstream>
#include <memory>
#include <optional>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "gmock/gmock.h"
#include "grpc/health/v1/health.grpc.pb.h"
#include "gtest/gtest.h"
#include "server/log.h"
#include "tests/server/server_test_util.h"

namespace fd::server {
namespace {

using ::testing::AllOf;
using ::testing::HasSubstr;
using namespace ::fd::server::testing;  // NOLINT(build/namespaces)

ServerOptions TinyOptions(std::vector<std::string> names = {kEmbeddedEnvironmentName}) {
  ServerOptions options;
  options.config = TestConfig();
  for (const std::string& name : names) options.environments.emplace_back(name, TinyEnvironment());
  return options;
}

// Opens a session and renders frames [first, first + count); returns the
// images' bytes in order. Fails the test on any unexpected message.
struct Rendered {
  std::string session_id;
  std::string resume_token;
  std::vector<std::string> images;
  std::vector<uint32_t> batch_sizes;  // FrameTimings.batch_size of each frame
};

Rendered OpenAndRender(StreamClient& stream, const v1::RenderRequest& open, uint64_t first,
                       int count) {
  Rendered out;
  EXPECT_TRUE(stream.Write(open));
  std::optional<v1::RenderResponse> opened = stream.Read();
  EXPECT_TRUE(opened.has_value() && opened->has_opened());
  if (!opened.has_value() || !opened->has_opened()) return out;
  out.session_id = opened->opened().session_id();
  out.resume_token = opened->opened().resume_token();
  for (int i = 0; i < count; ++i) {
    EXPECT_TRUE(stream.Write(MakeFrame(first + static_cast<uint64_t>(i))));
    std::optional<v1::RenderResponse> response = stream.Read();
    EXPECT_TRUE(response.has_value() && response->has_frame())
        << (response.has_value() ? response->DebugString() : "end of stream");
    if (!response.has_value() || !response->has_frame()) return out;
    EXPECT_EQ(response->frame().frame_index(), first + static_cast<uint64_t>(i));
    out.images.push_back(response->frame().image().data());
    out.batch_sizes.push_back(response->frame().timings().batch_size());
  }
  return out;
}

TEST(RenderServiceTest, ListEnvironmentsDescribesTheEmbeddedTrainedStreet) {
  ServerOptions options;
  options.config = TestConfig();  // no repository, no environments: the embedded default
  auto server = StartOrNull(std::move(options));
  ASSERT_NE(server, nullptr);
  auto stub = v1::FrameDiffuser::NewStub(Connect(*server));
  grpc::ClientContext context;
  v1::ListEnvironmentsResponse response;
  ASSERT_TRUE(stub->ListEnvironments(&context, {}, &response).ok());
  ASSERT_EQ(response.environments_size(), 1);
  const v1::Environment& env = response.environments(0);
  EXPECT_EQ(env.name(), "default");
  EXPECT_THAT(env.description(), AllOf(HasSubstr("Trained by framediffuser-train"),
                                       HasSubstr("stage3"), HasSubstr("street")));
  EXPECT_EQ(env.readiness(), v1::READINESS_READY);
  EXPECT_EQ(env.native_width(), 128u);
  EXPECT_EQ(env.native_height(), 128u);
  EXPECT_EQ(env.default_steps(), 1u);  // environments/street/environment.json
  EXPECT_EQ(env.default_scheduler(), v1::SCHEDULER_UNIPC);
  EXPECT_EQ(env.default_sky_mode(), v1::SKY_MODE_PREVIOUS_OUTPUT);
  EXPECT_EQ(env.min_size(), 16u);
  EXPECT_EQ(env.max_size(), 256u);
  EXPECT_EQ(env.max_steps(), 8u);
  EXPECT_FALSE(env.prompt().empty());
}

TEST(RenderServiceTest, TwentyFramesInOrderThenHalfCloseClosesTheSession) {
  auto server = StartOrNull(TinyOptions());
  ASSERT_NE(server, nullptr);
  ScopedLogCapture logs;
  StreamClient stream(Connect(*server));
  ASSERT_TRUE(stream.Write(MakeOpen()));
  std::optional<v1::RenderResponse> opened = stream.Read();
  ASSERT_TRUE(opened.has_value() && opened->has_opened());
  const v1::SessionSettings& settings = opened->opened().settings();
  EXPECT_EQ(settings.environment(), "default");
  EXPECT_EQ(settings.width(), kSize);
  EXPECT_EQ(settings.steps(), kSteps);
  EXPECT_EQ(settings.seed(), 7u);
  EXPECT_EQ(settings.output_dtype(), v1::DTYPE_UINT8);
  EXPECT_EQ(settings.max_frames_in_flight(), 2u);  // the server default
  EXPECT_FALSE(opened->opened().resumed());
  EXPECT_EQ(opened->opened().resume_token().size(), 32u);

  // Write every frame first (the stream reads ahead two at a time), then read.
  std::thread writer([&] {
    for (uint64_t i = 0; i < 20; ++i) EXPECT_TRUE(stream.Write(MakeFrame(10 + 3 * i)));
    stream.WritesDone();
  });
  std::vector<v1::RenderResponse> responses = stream.ReadAll();
  writer.join();
  EXPECT_TRUE(stream.Finish().ok());
  ASSERT_EQ(responses.size(), 20u);
  for (uint64_t i = 0; i < 20; ++i) {
    ASSERT_TRUE(responses[i].has_frame()) << responses[i].DebugString();
    const v1::RenderedFrame& frame = responses[i].frame();
    EXPECT_EQ(frame.frame_index(), 10 + 3 * i);
    EXPECT_EQ(frame.image().width(), kSize);
    EXPECT_EQ(frame.image().height(), kSize);
    EXPECT_EQ(frame.image().channels(), 3u);
    EXPECT_EQ(frame.image().dtype(), v1::DTYPE_UINT8);
    EXPECT_EQ(frame.image().data().size(), kSize * kSize * 3);
    EXPECT_GT(frame.timings().total_ms(), 0.0);
    EXPECT_GT(frame.timings().denoise_ms(), 0.0);
    EXPECT_GE(frame.timings().batch_size(), 1u);
  }
  // Consecutive frames differ (the chain advances).
  EXPECT_NE(responses[0].frame().image().data(), responses[1].frame().image().data());

  EXPECT_EQ(testing::AwaitSessionEnded(server->store(), opened->opened().session_id()),
            session::EndReason::kClosed);
  EXPECT_EQ(server->store().live_sessions(), 0u);
  // Logged just after the store closed the session.
  EXPECT_TRUE(testing::AwaitLogLine(logs, "\"event\":\"session_close\""));
  std::string log = absl::StrJoin(logs.lines(), "\n");
  EXPECT_THAT(log, HasSubstr("\"event\":\"session_open\""));
  EXPECT_THAT(log, ::testing::Not(HasSubstr(opened->opened().resume_token())));
}

TEST(RenderServiceTest, SameSeedAndInputsGiveTheSameFrames) {
  auto server = StartOrNull(TinyOptions());
  ASSERT_NE(server, nullptr);
  StreamClient a(Connect(*server));
  StreamClient b(Connect(*server));
  Rendered first = OpenAndRender(a, MakeOpen(kEmbeddedEnvironmentName, 99), 0, 3);
  Rendered second = OpenAndRender(b, MakeOpen(kEmbeddedEnvironmentName, 99), 0, 3);
  EXPECT_NE(first.session_id, second.session_id);
  EXPECT_EQ(first.images, second.images);
}

// Starts a server with `options` and renders frames 0..2 of `open`; with
// `beside`, a second session renders frames 0..2 of it at the same time on
// another stream.
Rendered RenderThreeFrames(ServerOptions options, const v1::RenderRequest& open,
                           std::optional<v1::RenderRequest> beside = std::nullopt) {
  auto server = StartOrNull(std::move(options));
  if (server == nullptr) {
    ADD_FAILURE() << "server did not start";
    return {};
  }
  StreamClient a(Connect(*server));
  std::unique_ptr<StreamClient> b;
  std::thread other;
  if (beside.has_value()) {
    b = std::make_unique<StreamClient>(Connect(*server));
    other = std::thread([&] { OpenAndRender(*b, *beside, 0, 3); });
  }
  Rendered got = OpenAndRender(a, open, 0, 3);
  if (other.joinable()) other.join();
  return got;
}

// Two batcher workers per environment: concurrent sessions render on
// either, and a session's frames stay the same as with one worker (its
// noise depends only on its seed and frame counter; batches of 1 here).
TEST(RenderServiceTest, TwoSchedulerWorkersRenderTheSameFrames) {
  // One LibTorch thread per worker in both servers, so that only the
  // worker count differs.
  ServerOptions one_worker = TinyOptions();
  one_worker.config.max_batch_size = 2;
  one_worker.config.threads = 1;
  const Rendered want =
      RenderThreeFrames(std::move(one_worker), MakeOpen(kEmbeddedEnvironmentName, 5));

  ServerOptions two_workers = TinyOptions();
  two_workers.config.scheduler_workers = 2;
  two_workers.config.max_batch_size = 2;  // one frame per worker batch
  two_workers.config.threads = 1;
  const Rendered got =
      RenderThreeFrames(std::move(two_workers), MakeOpen(kEmbeddedEnvironmentName, 5),
                        MakeOpen(kEmbeddedEnvironmentName, 6));
  EXPECT_EQ(got.images.size(), 3u);
  EXPECT_EQ(got.images, want.images);
}

// --batch_invariant: a session's frames while another session shares every
// batch are bitwise its frames alone. Float32 output, where frames batched
// without the option differ from the frames alone by float32 noise.
TEST(RenderServiceTest, BatchInvariantSharedFramesAreBitwiseAlone) {
  auto open_float = [](uint64_t seed) {
    v1::RenderRequest open = MakeOpen(kEmbeddedEnvironmentName, seed);
    open.mutable_open()->set_output_dtype(v1::DTYPE_FLOAT32);
    return open;
  };
  ServerOptions alone = TinyOptions();
  alone.config.max_batch_size = 1;
  alone.config.threads = 1;
  const Rendered want = RenderThreeFrames(std::move(alone), open_float(5));

  ServerOptions shared = TinyOptions();
  shared.config.batch_invariant = true;
  shared.config.scheduler_workers = 1;
  shared.config.max_batch_size = 2;
  shared.config.threads = 1;
  // Each batch waits for both sessions' frames (they advance in lockstep).
  shared.config.max_queue_delay = absl::Seconds(30);
  const Rendered got = RenderThreeFrames(std::move(shared), open_float(5), open_float(6));
  EXPECT_EQ(got.batch_sizes, std::vector<uint32_t>(3, 2));
  EXPECT_TRUE(got.images == want.images);
}

TEST(RenderServiceTest, ResumeAfterDisconnectContinuesTheChain) {
  auto server = StartOrNull(TinyOptions());
  ASSERT_NE(server, nullptr);

  // Reference: five frames without interruption.
  StreamClient reference(Connect(*server));
  Rendered expected = OpenAndRender(reference, MakeOpen(kEmbeddedEnvironmentName, 5), 0, 5);
  ASSERT_EQ(expected.images.size(), 5u);

  // Three frames, then the connection drops.
  Rendered before;
  {
    StreamClient stream(Connect(*server));
    before = OpenAndRender(stream, MakeOpen(kEmbeddedEnvironmentName, 5), 0, 3);
    stream.Cancel();
    EXPECT_EQ(stream.Finish().error_code(), grpc::StatusCode::CANCELLED);
  }
  EXPECT_EQ(server->store().live_sessions(), 2u);  // the reference's and this one

  StreamClient resumed(Connect(*server), {{"x-session-id", before.session_id}});
  ASSERT_TRUE(resumed.Write(MakeResume(before.session_id, before.resume_token)));
  std::optional<v1::RenderResponse> opened = resumed.Read();
  ASSERT_TRUE(opened.has_value() && opened->has_opened()) << opened->DebugString();
  EXPECT_TRUE(opened->opened().resumed());
  EXPECT_EQ(opened->opened().session_id(), before.session_id);
  EXPECT_TRUE(opened->opened().resume_token().empty());  // the secret is never sent again
  ASSERT_TRUE(opened->opened().has_last_frame_index());
  EXPECT_EQ(opened->opened().last_frame_index(), 2u);
  std::vector<std::string> images = before.images;
  for (uint64_t i = 3; i < 5; ++i) {
    ASSERT_TRUE(resumed.Write(MakeFrame(i)));
    std::optional<v1::RenderResponse> frame = resumed.Read();
    ASSERT_TRUE(frame.has_value() && frame->has_frame());
    images.push_back(frame->frame().image().data());
  }
  EXPECT_EQ(images, expected.images);
}

TEST(RenderServiceTest, OpenAdoptsTheClientsRoutingKey) {
  auto server = StartOrNull(TinyOptions());
  ASSERT_NE(server, nullptr);
  const std::string key = "00112233445566778899aabbccddeeff";
  StreamClient stream(Connect(*server), {{"x-session-id", key}});
  ASSERT_TRUE(stream.Write(MakeOpen()));
  std::optional<v1::RenderResponse> opened = stream.Read();
  ASSERT_TRUE(opened.has_value() && opened->has_opened());
  EXPECT_EQ(opened->opened().session_id(), key);
}

TEST(RenderServiceTest, TwoEnvironmentsServeConcurrently) {
  auto server = StartOrNull(TinyOptions({"street", "room"}));
  ASSERT_NE(server, nullptr);
  Rendered street, room;
  std::thread a([&] {
    StreamClient stream(Connect(*server));
    street = OpenAndRender(stream, MakeOpen("street"), 0, 4);
  });
  std::thread b([&] {
    StreamClient stream(Connect(*server));
    room = OpenAndRender(stream, MakeOpen("room"), 0, 4);
  });
  a.join();
  b.join();
  EXPECT_EQ(street.images.size(), 4u);
  EXPECT_EQ(room.images.size(), 4u);
  // The same model, seed and inputs: the same frames, from two schedulers.
  EXPECT_EQ(street.images, room.images);
  const std::string metrics = server->metrics().Scrape();
  EXPECT_THAT(metrics, HasSubstr("environment=\"street\""));
  EXPECT_THAT(metrics, HasSubstr("environment=\"room\""));
}

TEST(RenderServiceTest, HealthPerServerServiceAndEnvironment) {
  auto server = StartOrNull(TinyOptions({"street"}));
  ASSERT_NE(server, nullptr);
  auto health = grpc::health::v1::Health::NewStub(Connect(*server));
  auto check = [&](const std::string& service) {
    grpc::ClientContext context;
    grpc::health::v1::HealthCheckRequest request;
    request.set_service(service);
    grpc::health::v1::HealthCheckResponse response;
    grpc::Status status = health->Check(&context, request, &response);
    return status.ok() ? static_cast<int>(response.status())
                       : -static_cast<int>(status.error_code());
  };
  EXPECT_EQ(check(""), grpc::health::v1::HealthCheckResponse::SERVING);
  EXPECT_EQ(check("framediffuser.v1.FrameDiffuser"),
            grpc::health::v1::HealthCheckResponse::SERVING);
  EXPECT_EQ(check("framediffuser.v1.FrameDiffuser/street"),
            grpc::health::v1::HealthCheckResponse::SERVING);
  EXPECT_EQ(check("framediffuser.v1.FrameDiffuser/nope"), -grpc::StatusCode::NOT_FOUND);
}

TEST(RenderServiceTest, MetricsCountFramesSessionsAndStages) {
  ServerOptions options = TinyOptions();
  options.config.metrics_listen = "127.0.0.1:0";
  auto server = StartOrNull(std::move(options));
  ASSERT_NE(server, nullptr);
  EXPECT_GT(server->metrics_port(), 0);
  {
    StreamClient stream(Connect(*server));
    Rendered r = OpenAndRender(stream, MakeOpen(), 0, 3);
    stream.WritesDone();
    EXPECT_TRUE(stream.ReadAll().empty());
    EXPECT_TRUE(stream.Finish().ok());
  }
  const std::string metrics = server->metrics().Scrape();
  EXPECT_THAT(metrics,
              HasSubstr("framediffuser_frames_total{environment=\"default\",outcome=\"ok\"} 3"));
  EXPECT_THAT(metrics, HasSubstr("framediffuser_build_info{"));
  EXPECT_THAT(metrics, HasSubstr("framediffuser_frame_stage_seconds"));
  EXPECT_THAT(metrics, HasSubstr("framediffuser_model_loads_total"));
  EXPECT_THAT(metrics, ::testing::Not(HasSubstr("session_id")));
}

}  // namespace
}  // namespace fd::server

namespace fd::server {
namespace {

using namespace ::fd::server::testing;  // NOLINT(build/namespaces)

std::string TlsFile(const std::string& name) {
  return std::string(FD_SOURCE_DIR) + "/tests/client_sdk/testdata/tls/" + name;
}

std::string ReadText(const std::string& path) {
  std::ifstream in(path);
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

TEST(RenderServiceTlsTest, ServesOverTlsOnlyToClientsThatTrustIt) {
  ServerOptions options;
  options.config = TestConfig();
  options.config.tls_cert = TlsFile("localhost.crt");
  options.config.tls_key = TlsFile("localhost.key");
  options.environments.emplace_back(kEmbeddedEnvironmentName, TinyEnvironment());
  auto server = StartOrNull(std::move(options));
  ASSERT_NE(server, nullptr);
  const std::string target = absl::StrCat("localhost:", server->port());

  grpc::SslCredentialsOptions ssl;
  ssl.pem_root_certs = ReadText(TlsFile("localhost.crt"));
  auto trusted = v1::FrameDiffuser::NewStub(grpc::CreateChannel(target, grpc::SslCredentials(ssl)));
  grpc::ClientContext context;
  v1::ListEnvironmentsResponse response;
  grpc::Status status = trusted->ListEnvironments(&context, {}, &response);
  ASSERT_TRUE(status.ok()) << status.error_message();
  EXPECT_EQ(response.environments_size(), 1);

  auto plain =
      v1::FrameDiffuser::NewStub(grpc::CreateChannel(target, grpc::InsecureChannelCredentials()));
  grpc::ClientContext plain_context;
  plain_context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(30));
  EXPECT_FALSE(plain->ListEnvironments(&plain_context, {}, &response).ok());
}

TEST(RenderServiceTlsTest, UnreadableCertificateIsNamed) {
  ServerOptions options;
  options.config = TestConfig();
  options.config.tls_cert = TlsFile("missing.crt");
  options.config.tls_key = TlsFile("localhost.key");
  options.environments.emplace_back(kEmbeddedEnvironmentName, TinyEnvironment());
  absl::StatusOr<std::unique_ptr<FrameDiffuserServer>> server =
      FrameDiffuserServer::Start(std::move(options));
  ASSERT_FALSE(server.ok());
  EXPECT_EQ(server.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(server.status().message()), ::testing::HasSubstr("--tls_cert"));
}

}  // namespace
}  // namespace fd::server

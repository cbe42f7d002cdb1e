// The SDK (Client, Session) against the in-process FakeRenderServer:
// environments, health, blocking and asynchronous rendering, ordering,
// pipelining, re-seed, close and error propagation.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <future>
#include <limits>
#include <sstream>
#include <thread>

#include "client_sdk/client.h"
#include "tests/client_sdk/sdk_fixture.h"

namespace fd::client {
namespace {

using testing::ExpectedOutput;
using testing::ExpectedSequence;
using ::testing::HasSubstr;
using testing::kSize;
using testing::MakeFrames;
using testing::Pattern8;
using testing::ResultLog;
using testing::SdkTest;
using testing::TestFrame;

bool IsHex32(const std::string& s) {
  return s.size() == 32 && s.find_first_not_of("0123456789abcdef") == std::string::npos;
}

TEST_F(SdkTest, ListsEnvironments) {
  absl::StatusOr<std::vector<Environment>> environments = client_->ListEnvironments();
  ASSERT_TRUE(environments.ok()) << environments.status();
  ASSERT_EQ(environments->size(), 1u);
  const Environment& tiny = environments->front();
  EXPECT_EQ(tiny.name, "tiny");
  EXPECT_EQ(tiny.readiness, Readiness::kReady);
  EXPECT_EQ(tiny.native_width, 16u);
  EXPECT_EQ(tiny.max_steps, 8u);
  EXPECT_EQ(tiny.default_scheduler, Scheduler::kUniPC);
  EXPECT_EQ(tiny.default_sky_mode, SkyMode::kPreviousOutput);
}

TEST_F(SdkTest, ChecksHealth) {
  absl::StatusOr<HealthStatus> overall = client_->CheckHealth();
  ASSERT_TRUE(overall.ok()) << overall.status();
  EXPECT_EQ(*overall, HealthStatus::kServing);
  absl::StatusOr<HealthStatus> service = client_->CheckHealth("framediffuser.v1.FrameDiffuser");
  ASSERT_TRUE(service.ok()) << service.status();
  EXPECT_EQ(*service, HealthStatus::kServing);
  EXPECT_EQ(client_->CheckHealth("no.such.Service").status().code(), absl::StatusCode::kNotFound);
}

TEST_F(SdkTest, UnreachableServerIsUnavailableNamingTheTarget) {
  const std::string address = server_->address();
  server_->Stop();
  absl::StatusOr<std::vector<Environment>> environments = client_->ListEnvironments();
  EXPECT_EQ(environments.status().code(), absl::StatusCode::kUnavailable);
  EXPECT_THAT(environments.status().message(), HasSubstr("cannot reach"));
  EXPECT_THAT(environments.status().message(), HasSubstr(address));
  absl::StatusOr<std::unique_ptr<Session>> session = client_->OpenSession(DefaultSessionOptions());
  EXPECT_EQ(session.status().code(), absl::StatusCode::kUnavailable);
  EXPECT_THAT(session.status().message(), HasSubstr(address));
}

TEST_F(SdkTest, BlockingRenderFromKeyframe) {
  const std::vector<TestFrame> frames = MakeFrames(6);
  const Image8 keyframe = Pattern8(kSize, kSize, 3, 999);
  SessionOptions options = DefaultSessionOptions();
  options.keyframe = ImageView::Of(keyframe);
  std::unique_ptr<Session> session = Open(options);
  ASSERT_NE(session, nullptr);
  const SessionSettings settings = session->settings();
  EXPECT_EQ(settings.environment, "tiny");
  EXPECT_EQ(settings.width, 16u);
  EXPECT_EQ(settings.seed, 7u);
  EXPECT_EQ(settings.steps, 4u);  // the environment's default
  EXPECT_TRUE(settings.started_from_keyframe);
  EXPECT_EQ(session->frames_in_flight(), 2u);

  const std::vector<Image8> expected = ExpectedSequence(frames, keyframe);
  for (size_t i = 0; i < frames.size(); ++i) {
    absl::StatusOr<Frame> frame = session->Render(frames[i].request());
    ASSERT_TRUE(frame.ok()) << frame.status();
    EXPECT_EQ(frame->frame_index, i);
    EXPECT_EQ(frame->dtype, DType::kUint8);
    EXPECT_EQ(frame->timings.batch_size, 1u);
    EXPECT_EQ(frame->ToImage8(), expected[i]) << "frame " << i;
  }
  EXPECT_TRUE(session->Close().ok());
  EXPECT_TRUE(session->Close().ok());  // idempotent
  EXPECT_EQ(session->Render(TestFrame(6).request()).status().code(),
            absl::StatusCode::kFailedPrecondition);
  // The open carried a client-generated x-session-id that the (fake) server
  // adopted as the session id, so a hash-based balancer routes resumes alike.
  const std::vector<std::string> headers = server_->x_session_id_headers();
  ASSERT_EQ(headers.size(), 1u);
  EXPECT_TRUE(IsHex32(headers[0])) << headers[0];
  EXPECT_EQ(session->session_id(), headers[0]);
  EXPECT_EQ(session->failover_count(), 0);
}

TEST_F(SdkTest, AsyncCallbacksArriveInOrder) {
  const std::vector<TestFrame> frames = MakeFrames(20);
  std::unique_ptr<Session> session = Open(DefaultSessionOptions());
  ASSERT_NE(session, nullptr);
  ResultLog log;
  for (const TestFrame& frame : frames) {
    ASSERT_TRUE(session
                    ->Submit(frame.request(),
                             [&log, index = frame.index](absl::StatusOr<Frame> result) {
                               log.Add(std::move(result), index);
                             })
                    .ok());
  }
  ASSERT_TRUE(log.WaitFor(frames.size()));
  const std::vector<Image8> expected = ExpectedSequence(frames);
  const std::vector<absl::StatusOr<Frame>> results = log.results();
  for (size_t i = 0; i < frames.size(); ++i) {
    ASSERT_TRUE(results[i].ok()) << results[i].status();
    EXPECT_EQ(results[i]->frame_index, i);
    EXPECT_EQ(log.indices()[i], i);
    EXPECT_EQ(results[i]->ToImage8(), expected[i]);
  }
  EXPECT_TRUE(session->Close().ok());
}

TEST_F(SdkTest, FuturesAndOutputDtypesWithCompression) {
  const std::vector<TestFrame> frames = MakeFrames(5);
  SessionOptions options = DefaultSessionOptions();
  options.output_dtype = DType::kFloat16;
  options.output_compression = Compression::kZstd;
  options.input_compression = Compression::kZstd;
  std::unique_ptr<Session> session = Open(options);
  ASSERT_NE(session, nullptr);
  EXPECT_EQ(session->settings().output_dtype, DType::kFloat16);
  std::vector<std::future<absl::StatusOr<Frame>>> futures;
  for (const TestFrame& frame : frames) futures.push_back(session->RenderAsync(frame.request()));
  // The fake's model in float, quantised to float16 as the output.
  ImageF previous;
  for (size_t i = 0; i < frames.size(); ++i) {
    absl::StatusOr<Frame> frame = futures[i].get();
    ASSERT_TRUE(frame.ok()) << frame.status();
    ASSERT_EQ(frame->dtype, DType::kFloat16);
    const ImageF expected =
        ToFloat(ImageView::Of(ToHalf(ImageView::Of(fd::testing::FakeRenderServer::Render(
            ToFloat(ImageView::Of(frames[i].basecolor)), ToFloat(ImageView::Of(frames[i].depth)),
            previous)))));
    EXPECT_EQ(frame->ToFloat(), expected) << "frame " << i;
    previous = expected;
  }
  EXPECT_TRUE(session->Close().ok());
}

TEST_F(SdkTest, PipelinesWithinTheWindow) {
  // The server would accept 4 frames in flight; the client asks for 2.
  const std::vector<TestFrame> frames = MakeFrames(8);
  std::unique_ptr<Session> session = Open(DefaultSessionOptions());
  ASSERT_NE(session, nullptr);
  ASSERT_EQ(session->frames_in_flight(), 2u);
  server_->PauseRendering();
  ResultLog log;
  auto submit = [&](const TestFrame& frame) {
    return session->Submit(frame.request(), [&log, index = frame.index](absl::StatusOr<Frame> r) {
      log.Add(std::move(r), index);
    });
  };
  ASSERT_TRUE(submit(frames[0]).ok());
  ASSERT_TRUE(submit(frames[1]).ok());
  // Frame 1 is uploaded while frame 0 is still unrendered: pipelining.
  ASSERT_TRUE(server_->WaitForFramesReceived(2, absl::Seconds(30)));
  // A third Submit has to wait for a free slot.
  std::future<absl::Status> third =
      std::async(std::launch::async, [&] { return submit(frames[2]); });
  EXPECT_NE(third.wait_for(std::chrono::seconds(0)), std::future_status::ready);
  EXPECT_EQ(server_->frames_received(), 2);
  server_->ResumeRendering();
  ASSERT_TRUE(third.get().ok());
  for (size_t i = 3; i < frames.size(); ++i) ASSERT_TRUE(submit(frames[i]).ok());
  ASSERT_TRUE(log.WaitFor(frames.size()));
  const std::vector<Image8> expected = ExpectedSequence(frames);
  for (size_t i = 0; i < frames.size(); ++i) {
    ASSERT_TRUE(log.results()[i].ok());
    EXPECT_EQ(log.results()[i]->ToImage8(), expected[i]);
  }
  // Never more than the window outstanding at the server, and the window used.
  EXPECT_EQ(server_->max_outstanding_frames(), 2);
  EXPECT_TRUE(session->Close().ok());
}

TEST_F(SdkTest, ReseedWithKeyframe) {
  const std::vector<TestFrame> frames = MakeFrames(6);
  std::unique_ptr<Session> session = Open(DefaultSessionOptions());
  ASSERT_NE(session, nullptr);
  const Image8 cut = Pattern8(kSize, kSize, 3, 4242);
  Image8 previous;
  for (const TestFrame& frame : frames) {
    FrameRequest request = frame.request();
    if (frame.index == 3) request.keyframe = ImageView::Of(cut);  // a camera cut
    absl::StatusOr<Frame> rendered = session->Render(request);
    ASSERT_TRUE(rendered.ok()) << rendered.status();
    const Image8 expected = ExpectedOutput(frame, frame.index == 3 ? cut : previous);
    EXPECT_EQ(rendered->ToImage8(), expected) << "frame " << frame.index;
    previous = expected;
  }
  EXPECT_TRUE(session->Close().ok());
}

TEST_F(SdkTest, EngineLayoutsRgbaAndPackedChannels) {
  const TestFrame frame(0);
  // Basecolor as RGBA with padded rows, depth as the B channel of a packed
  // RGBA texture: the SDK converts while copying.
  const int stride = kSize * 4 + 8;
  std::vector<uint8_t> rgba(size_t(stride) * kSize, 0xEE);
  std::vector<uint8_t> packed(size_t(kSize) * kSize * 4, 0);
  for (int y = 0; y < kSize; ++y) {
    for (int x = 0; x < kSize; ++x) {
      for (int c = 0; c < 3; ++c)
        rgba[size_t(y) * stride + x * 4 + c] = frame.basecolor.at(x, y, c);
      packed[(size_t(y) * kSize + x) * 4 + 2] = frame.depth.at(x, y, 0);
    }
  }
  FrameRequest request = frame.request();
  request.gbuffer.basecolor = ImageView::Raw(rgba.data(), kSize, kSize, 4, DType::kUint8, stride);
  request.gbuffer.depth = ImageView::Raw(packed.data(), kSize, kSize, 4, DType::kUint8);
  request.gbuffer.depth.select_channel = 2;
  std::unique_ptr<Session> session = Open(DefaultSessionOptions());
  ASSERT_NE(session, nullptr);
  absl::StatusOr<Frame> rendered = session->Render(request);
  ASSERT_TRUE(rendered.ok()) << rendered.status();
  EXPECT_EQ(rendered->ToImage8(), ExpectedOutput(frame, Image8()));
}

TEST_F(SdkTest, LocalValidationErrors) {
  std::unique_ptr<Session> session = Open(DefaultSessionOptions());
  ASSERT_NE(session, nullptr);
  const TestFrame frame(0);
  FrameRequest missing = frame.request();
  missing.gbuffer.normals = ImageView();
  absl::Status status = session->Submit(missing, nullptr);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(status.message(), HasSubstr("frame.gbuffer.normals: missing"));

  const Image8 small = Pattern8(8, 8, 1, 1);
  FrameRequest wrong_size = frame.request();
  wrong_size.gbuffer.depth = ImageView::Of(small);
  status = session->Submit(wrong_size, nullptr);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(status.message(),
              HasSubstr("frame.gbuffer.depth: expected the session's size 16x16"));

  FrameRequest three_channel_depth = frame.request();
  three_channel_depth.gbuffer.depth = ImageView::Of(frame.basecolor);
  status = session->Submit(three_channel_depth, nullptr);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(status.message(), HasSubstr("select_channel"));

  ASSERT_TRUE(session->Render(TestFrame(5).request()).ok());
  status = session->Submit(TestFrame(5).request(), nullptr);
  EXPECT_EQ(status.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(status.message(), HasSubstr("must be greater than the previous frame's 5"));
}

TEST_F(SdkTest, FrameErrorFailsOnlyThatFrame) {
  const std::vector<TestFrame> frames = MakeFrames(4);
  std::unique_ptr<Session> session = Open(DefaultSessionOptions());
  ASSERT_NE(session, nullptr);
  ASSERT_TRUE(session->Render(frames[0].request()).ok());
  // Float depth with a NaN: the client forwards it, the server rejects it.
  ImageF bad_depth = ToFloat(ImageView::Of(frames[1].depth));
  bad_depth.pixels[17] = std::numeric_limits<float>::quiet_NaN();
  FrameRequest bad = frames[1].request();
  bad.gbuffer.depth = ImageView::Of(bad_depth);
  absl::StatusOr<Frame> rejected = session->Render(bad);
  EXPECT_EQ(rejected.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(rejected.status().message(), HasSubstr("frame.gbuffer.depth"));
  // The session goes on; the rejected frame may be retried with its index,
  // and continues from frame 0's output.
  const std::vector<Image8> expected = ExpectedSequence(frames);
  for (size_t i = 1; i < frames.size(); ++i) {
    absl::StatusOr<Frame> frame = session->Render(frames[i].request());
    ASSERT_TRUE(frame.ok()) << frame.status();
    EXPECT_EQ(frame->ToImage8(), expected[i]);
  }
  EXPECT_TRUE(session->Close().ok());
}

TEST_F(SdkTest, OpenErrorsCarryTheServersCodeAndMessage) {
  SessionOptions unknown = DefaultSessionOptions();
  unknown.environment = "nope";
  absl::StatusOr<std::unique_ptr<Session>> session = client_->OpenSession(unknown);
  EXPECT_EQ(session.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(session.status().message(), HasSubstr("open.environment"));

  SessionOptions bad_size = DefaultSessionOptions();
  bad_size.width = 12;
  session = client_->OpenSession(bad_size);
  EXPECT_EQ(session.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(session.status().message(), HasSubstr("open.width"));

  server_->FailNextOpen(static_cast<int>(absl::StatusCode::kResourceExhausted), "session limit 1");
  session = client_->OpenSession(DefaultSessionOptions());
  EXPECT_EQ(session.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_THAT(session.status().message(), HasSubstr("session limit 1"));

  SessionOptions no_environment;
  EXPECT_EQ(client_->OpenSession(no_environment).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST_F(SdkTest, StreamErrorWithoutFailoverFailsOutstandingFrames) {
  SessionOptions options = DefaultSessionOptions();
  options.failover = false;
  std::unique_ptr<Session> session = Open(options);
  ASSERT_NE(session, nullptr);
  ASSERT_TRUE(session->Render(TestFrame(0).request()).ok());
  server_->BreakOnFrame(1, fd::testing::FakeRenderServer::BreakPoint::kBeforeRender);
  absl::StatusOr<Frame> broken = session->Render(TestFrame(1).request());
  EXPECT_EQ(broken.status().code(), absl::StatusCode::kUnavailable);
  EXPECT_THAT(broken.status().message(), HasSubstr("fake: stream broken before render"));
  // The session is over: later calls report why.
  EXPECT_EQ(session->Render(TestFrame(2).request()).status().code(),
            absl::StatusCode::kUnavailable);
  EXPECT_EQ(session->Close().code(), absl::StatusCode::kUnavailable);
  EXPECT_EQ(session->failover_count(), 0);
}

TEST_F(SdkTest, DestroyingAnOpenSessionCancelsOutstandingFrames) {
  std::unique_ptr<Session> session = Open(DefaultSessionOptions());
  ASSERT_NE(session, nullptr);
  server_->PauseRendering();
  std::future<absl::StatusOr<Frame>> pending = session->RenderAsync(TestFrame(0).request());
  ASSERT_TRUE(server_->WaitForFramesReceived(1, absl::Seconds(30)));
  session.reset();
  EXPECT_EQ(pending.get().status().code(), absl::StatusCode::kCancelled);
  server_->ResumeRendering();
}

class SdkAuthTest : public SdkTest {
 protected:
  void SetUp() override {
    fd::testing::FakeRenderServerOptions options;
    options.required_token = "s3cret";
    StartServer(options);
  }
};

TEST_F(SdkAuthTest, BearerTokenIsSentOnEveryCall) {
  EXPECT_EQ(client_->ListEnvironments().status().code(), absl::StatusCode::kUnauthenticated);
  client_ = MakeClient("s3cret");
  ASSERT_TRUE(client_->ListEnvironments().ok());
  std::unique_ptr<Session> session = Open(DefaultSessionOptions());
  ASSERT_NE(session, nullptr);
  ASSERT_TRUE(session->Render(TestFrame(0).request()).ok());
  EXPECT_TRUE(session->Close().ok());
  const std::vector<std::string> seen = server_->authorization_headers();
  ASSERT_EQ(seen.size(), 3u);
  EXPECT_EQ(seen[0], "");
  EXPECT_EQ(seen[1], "Bearer s3cret");
  EXPECT_EQ(seen[2], "Bearer s3cret");
}

}  // namespace
}  // namespace fd::client

namespace fd::client {
namespace {

std::string ReadTestFile(const std::string& name) {
  std::ifstream in(std::string(FD_SOURCE_DIR) + "/tests/client_sdk/testdata/tls/" + name);
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

class SdkTlsTest : public testing::SdkTest {
 protected:
  void SetUp() override {
    fd::testing::FakeRenderServerOptions options;
    options.tls_cert_pem = ReadTestFile("localhost.crt");
    options.tls_key_pem = ReadTestFile("localhost.key");
    ASSERT_FALSE(options.tls_cert_pem.empty());
    StartServer(options);
  }

  std::unique_ptr<Client> TlsClient(const std::string& roots) {
    ClientOptions options;
    options.target = server_->address();
    options.use_tls = true;
    options.tls_root_certs_pem = roots;
    absl::StatusOr<std::unique_ptr<Client>> client = Client::Create(options);
    EXPECT_TRUE(client.ok()) << client.status();
    return client.ok() ? std::move(*client) : nullptr;
  }
};

TEST_F(SdkTlsTest, ConnectsWithTheRightRootsOnly) {
  // An insecure client cannot talk to a TLS server.
  EXPECT_EQ(client_->ListEnvironments().status().code(), absl::StatusCode::kUnavailable);
  std::unique_ptr<Client> trusted = TlsClient(ReadTestFile("localhost.crt"));
  ASSERT_NE(trusted, nullptr);
  absl::StatusOr<std::vector<Environment>> environments = trusted->ListEnvironments();
  ASSERT_TRUE(environments.ok()) << environments.status();
  EXPECT_EQ(environments->front().name, "tiny");
  SessionOptions options = DefaultSessionOptions();
  absl::StatusOr<std::unique_ptr<Session>> session = trusted->OpenSession(options);
  ASSERT_TRUE(session.ok()) << session.status();
  EXPECT_TRUE((*session)->Render(testing::TestFrame(0).request()).ok());
  EXPECT_TRUE((*session)->Close().ok());
  // The system roots do not trust a self-signed certificate.
  std::unique_ptr<Client> untrusted = TlsClient("");
  ASSERT_NE(untrusted, nullptr);
  EXPECT_EQ(untrusted->ListEnvironments().status().code(), absl::StatusCode::kUnavailable);
}

}  // namespace
}  // namespace fd::client

// The SDK against the real server (fd::server::FrameDiffuserServer) running
// in-process on port 0 with the tiny random-weight environment: blocking and
// asynchronous rendering, determinism through the SDK, ordering, re-seed,
// close, errors, and failover — a server stopped (graceful drain) and
// restarted on the same port mid-sequence, and a broken connection to a
// server that keeps the session (resume, through a TCP forwarder).
//
// What the real model allows to assert: a session's frame k is a pure
// function of (seed, k, its conditioning), where k counts the frames the
// session rendered (session/frame_seed.h). So equal seeds and inputs give
// equal frames, a resumed session continues bit for bit, a re-seeded frame
// no longer depends on the history, and the new session that failover opens
// (its frame counter starts at 0 again) renders exactly what any fresh
// session opened from the last received frame renders.
#include <arpa/inet.h>
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <condition_variable>
#include <future>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "client_sdk/client.h"
#include "tests/client_sdk/sdk_fixture.h"
#include "tests/client_sdk/test_util.h"
#include "tests/server/server_test_util.h"

namespace fd::client {
namespace {

namespace srv = ::fd::server;
using ::fd::client::testing::Pattern8;
using ::testing::HasSubstr;

constexpr int kSide = 32;  // frame size (the environment's sizes are 16..256)
constexpr uint32_t kSteps = 2;
constexpr char kEnvironment[] = "default";

// The G-buffer of frame `index` (pixels owned here; requests hold views).
struct GFrame {
  uint64_t index = 0;
  Image8 basecolor, normals, depth, roughness;

  explicit GFrame(uint64_t i)
      : index(i),
        basecolor(Pattern8(kSide, kSide, 3, 100 + int(i))),
        normals(Pattern8(kSide, kSide, 3, 200 + int(i))),
        depth(Pattern8(kSide, kSide, 1, 300 + int(i))),
        roughness(Pattern8(kSide, kSide, 1, 400 + int(i))) {}

  FrameRequest request() const {
    FrameRequest request;
    request.frame_index = index;
    request.gbuffer.basecolor = ImageView::Of(basecolor);
    request.gbuffer.normals = ImageView::Of(normals);
    request.gbuffer.depth = ImageView::Of(depth);
    request.gbuffer.roughness = ImageView::Of(roughness);
    return request;
  }
};

std::vector<GFrame> MakeFrames(int first, int count) {
  std::vector<GFrame> frames;
  for (int i = first; i < first + count; ++i) frames.emplace_back(i);
  return frames;
}

// A rendered frame is well formed: the index asked for, the session's size,
// RGB uint8.
void ExpectFrame(const absl::StatusOr<Frame>& frame, uint64_t index) {
  ASSERT_TRUE(frame.ok()) << "frame " << index << ": " << frame.status();
  EXPECT_EQ(frame->frame_index, index);
  EXPECT_EQ(frame->width, kSide);
  EXPECT_EQ(frame->height, kSide);
  EXPECT_EQ(frame->channels, 3);
  EXPECT_EQ(frame->dtype, DType::kUint8);
  ASSERT_NE(frame->data, nullptr);
  EXPECT_EQ(frame->data->size(), size_t(kSide) * kSide * 3);
  EXPECT_GE(frame->timings.batch_size, 1u);
}

using ::fd::client::testing::ResultLog;

// A TCP forwarder between the SDK and the server, so that a test can break
// the connection (as a network blip or a proxy restart would) while the
// server keeps the session. BreakAll() cuts every open connection; the
// listener stays, so the client reconnects through it. Thread-safe.
class TcpForwarder {
 public:
  explicit TcpForwarder(int upstream_port) : upstream_port_(upstream_port) {
    listen_fd_ = ::socket(AF_INET, SOCK_STREAM, 0);
    if (listen_fd_ < 0) return;
    sockaddr_in address = Loopback(0);
    socklen_t length = sizeof(address);
    if (::bind(listen_fd_, reinterpret_cast<sockaddr*>(&address), sizeof(address)) != 0 ||
        ::listen(listen_fd_, 16) != 0 ||
        ::getsockname(listen_fd_, reinterpret_cast<sockaddr*>(&address), &length) != 0) {
      return;
    }
    port_ = ntohs(address.sin_port);
    acceptor_ = std::thread([this] { AcceptLoop(); });
  }

  ~TcpForwarder() {
    {
      std::lock_guard<std::mutex> lock(mu_);
      stopping_ = true;
    }
    if (listen_fd_ >= 0) ::shutdown(listen_fd_, SHUT_RDWR);  // wakes accept()
    if (acceptor_.joinable()) acceptor_.join();
    BreakAll();
    for (const std::unique_ptr<Link>& link : links_) {
      link->to_server.join();
      link->to_client.join();
      ::close(link->client_fd);
      ::close(link->server_fd);
    }
    if (listen_fd_ >= 0) ::close(listen_fd_);
  }

  TcpForwarder(const TcpForwarder&) = delete;
  TcpForwarder& operator=(const TcpForwarder&) = delete;

  bool ok() const { return port_ != 0; }
  std::string address() const { return absl::StrCat("127.0.0.1:", port_); }

  void BreakAll() {
    std::lock_guard<std::mutex> lock(mu_);
    for (const std::unique_ptr<Link>& link : links_) Cut(*link);
  }

  int connections() const {
    std::lock_guard<std::mutex> lock(mu_);
    return static_cast<int>(links_.size());
  }

 private:
  struct Link {
    int client_fd = -1;
    int server_fd = -1;
    std::thread to_server, to_client;
  };

  static sockaddr_in Loopback(int port) {
    sockaddr_in address{};
    address.sin_family = AF_INET;
    address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    address.sin_port = htons(static_cast<uint16_t>(port));
    return address;
  }

  // shutdown (not close) so that the descriptors stay ours until joined.
  static void Cut(const Link& link) {
    ::shutdown(link.client_fd, SHUT_RDWR);
    ::shutdown(link.server_fd, SHUT_RDWR);
  }

  // Copies one direction until either side ends, then cuts both.
  static void Pump(const Link* link, int from, int to) {
    char buffer[16384];
    for (;;) {
      const ssize_t n = ::recv(from, buffer, sizeof(buffer), 0);
      if (n < 0 && errno == EINTR) continue;
      if (n <= 0) break;
      ssize_t sent = 0;
      while (sent < n) {
        const ssize_t w = ::send(to, buffer + sent, size_t(n - sent), MSG_NOSIGNAL);
        if (w < 0 && errno == EINTR) continue;
        if (w <= 0) break;
        sent += w;
      }
      if (sent < n) break;
    }
    Cut(*link);
  }

  void AcceptLoop() {
    for (;;) {
      const int client = ::accept(listen_fd_, nullptr, nullptr);
      if (client < 0) {
        if (errno == EINTR) continue;
        return;  // shut down
      }
      const int server = ::socket(AF_INET, SOCK_STREAM, 0);
      const sockaddr_in upstream = Loopback(upstream_port_);
      if (server < 0 ||
          ::connect(server, reinterpret_cast<const sockaddr*>(&upstream), sizeof(upstream)) != 0) {
        if (server >= 0) ::close(server);
        ::close(client);
        continue;
      }
      std::lock_guard<std::mutex> lock(mu_);
      if (stopping_) {
        ::close(server);
        ::close(client);
        return;
      }
      auto link = std::make_unique<Link>();
      link->client_fd = client;
      link->server_fd = server;
      Link* raw = link.get();
      link->to_server = std::thread([raw] { Pump(raw, raw->client_fd, raw->server_fd); });
      link->to_client = std::thread([raw] { Pump(raw, raw->server_fd, raw->client_fd); });
      links_.push_back(std::move(link));
    }
  }

  const int upstream_port_;
  int listen_fd_ = -1;
  int port_ = 0;
  mutable std::mutex mu_;
  bool stopping_ = false;
  std::vector<std::unique_ptr<Link>> links_;
  std::thread acceptor_;  // last: starts after the members it uses
};

class RealServerTest : public ::testing::Test {
 protected:
  void SetUp() override {
    server_ = StartServer("127.0.0.1:0");
    ASSERT_NE(server_, nullptr);
    client_ = MakeClient(server_->address());
    ASSERT_NE(client_, nullptr);
  }

  static std::unique_ptr<srv::FrameDiffuserServer> StartServer(const std::string& listen) {
    srv::ServerOptions options;
    options.config = srv::testing::TestConfig();
    options.config.listen = listen;
    options.environments.emplace_back(kEnvironment, srv::testing::TinyEnvironment());
    absl::StatusOr<std::unique_ptr<srv::FrameDiffuserServer>> server =
        srv::FrameDiffuserServer::Start(std::move(options));
    EXPECT_TRUE(server.ok()) << server.status();
    return server.ok() ? *std::move(server) : nullptr;
  }

  static std::unique_ptr<Client> MakeClient(const std::string& target) {
    ClientOptions options;
    options.target = target;
    options.max_reconnect_backoff = absl::Milliseconds(100);
    absl::StatusOr<std::unique_ptr<Client>> client = Client::Create(options);
    EXPECT_TRUE(client.ok()) << client.status();
    return client.ok() ? *std::move(client) : nullptr;
  }

  SessionOptions Options(uint64_t seed = 7) {
    SessionOptions options;
    options.environment = kEnvironment;
    options.width = kSide;
    options.height = kSide;
    options.steps = kSteps;
    options.seed = seed;
    options.failover_timeout = absl::Seconds(60);
    options.on_failover = [this](const FailoverEvent& event) {
      std::lock_guard<std::mutex> lock(mu_);
      events_.push_back(event);
    };
    return options;
  }

  std::unique_ptr<Session> Open(const SessionOptions& options, Client* client = nullptr) {
    absl::StatusOr<std::unique_ptr<Session>> session =
        (client != nullptr ? client : client_.get())->OpenSession(options);
    EXPECT_TRUE(session.ok()) << session.status();
    return session.ok() ? *std::move(session) : nullptr;
  }

  // Renders `frames` one at a time (blocking); returns their pixels.
  static std::vector<std::string> RenderBlocking(Session* session,
                                                 const std::vector<GFrame>& frames) {
    std::vector<std::string> pixels;
    for (const GFrame& frame : frames) {
      absl::StatusOr<Frame> rendered = session->Render(frame.request());
      ExpectFrame(rendered, frame.index);
      if (!rendered.ok() || rendered->data == nullptr) return pixels;
      pixels.push_back(*rendered->data);
    }
    return pixels;
  }

  // A fresh session with `options` renders `frames` and is closed.
  std::vector<std::string> RenderSequence(const SessionOptions& options,
                                          const std::vector<GFrame>& frames) {
    std::unique_ptr<Session> session = Open(options);
    if (session == nullptr) return {};
    std::vector<std::string> pixels = RenderBlocking(session.get(), frames);
    EXPECT_TRUE(session->Close().ok());
    return pixels;
  }

  std::vector<FailoverEvent> events() {
    std::lock_guard<std::mutex> lock(mu_);
    return events_;
  }

  std::unique_ptr<srv::FrameDiffuserServer> server_;
  std::unique_ptr<Client> client_;
  std::mutex mu_;
  std::vector<FailoverEvent> events_;
};

TEST_F(RealServerTest, BlockingRenderIsDeterministicPerSeed) {
  const std::vector<GFrame> frames = MakeFrames(0, 6);
  std::unique_ptr<Session> session = Open(Options(7));
  ASSERT_NE(session, nullptr);
  const SessionSettings settings = session->settings();
  EXPECT_EQ(settings.environment, kEnvironment);
  EXPECT_EQ(settings.width, uint32_t(kSide));
  EXPECT_EQ(settings.height, uint32_t(kSide));
  EXPECT_EQ(settings.seed, 7u);
  EXPECT_EQ(settings.steps, kSteps);
  EXPECT_EQ(settings.scheduler, Scheduler::kUniPC);  // the environment's default
  EXPECT_FALSE(settings.started_from_keyframe);
  EXPECT_EQ(session->frames_in_flight(), 2u);
  EXPECT_EQ(session->session_id().size(), 32u);

  const std::vector<std::string> first = RenderBlocking(session.get(), frames);
  ASSERT_EQ(first.size(), frames.size());
  for (size_t i = 1; i < first.size(); ++i) {
    EXPECT_NE(first[i], first[i - 1]) << "frames " << i - 1 << " and " << i;
  }
  EXPECT_TRUE(session->Close().ok());
  EXPECT_EQ(session->failover_count(), 0);

  // The same seed and inputs in another session: the same frames.
  EXPECT_EQ(RenderSequence(Options(7), frames), first);
  // Another seed: other noise, other frames.
  const std::vector<std::string> other = RenderSequence(Options(8), MakeFrames(0, 1));
  ASSERT_EQ(other.size(), 1u);
  EXPECT_NE(other[0], first[0]);
}

TEST_F(RealServerTest, PipelinedCallbacksAndFuturesMatchBlockingRender) {
  const std::vector<GFrame> frames = MakeFrames(0, 10);
  const std::vector<std::string> expected = RenderSequence(Options(11), frames);
  ASSERT_EQ(expected.size(), frames.size());

  // Callbacks: every frame submitted at once (Submit blocks for a window
  // slot), answered in submission order with the blocking run's pixels.
  {
    std::unique_ptr<Session> session = Open(Options(11));
    ASSERT_NE(session, nullptr);
    ResultLog log;
    for (const GFrame& frame : frames) {
      ASSERT_TRUE(session
                      ->Submit(frame.request(),
                               [&log, index = frame.index](absl::StatusOr<Frame> result) {
                                 log.Add(std::move(result), index);
                               })
                      .ok());
    }
    ASSERT_TRUE(log.WaitFor(frames.size()));
    const std::vector<absl::StatusOr<Frame>> results = log.results();
    const std::vector<uint64_t> order = log.indices();
    for (size_t i = 0; i < frames.size(); ++i) {
      EXPECT_EQ(order[i], i);
      ExpectFrame(results[i], i);
      ASSERT_TRUE(results[i].ok());
      EXPECT_EQ(*results[i]->data, expected[i]) << "frame " << i;
    }
    EXPECT_TRUE(session->Close().ok());
  }

  // Futures, likewise.
  {
    std::unique_ptr<Session> session = Open(Options(11));
    ASSERT_NE(session, nullptr);
    std::vector<std::future<absl::StatusOr<Frame>>> futures;
    for (const GFrame& frame : frames) futures.push_back(session->RenderAsync(frame.request()));
    for (size_t i = 0; i < frames.size(); ++i) {
      absl::StatusOr<Frame> result = futures[i].get();
      ExpectFrame(result, i);
      ASSERT_TRUE(result.ok());
      EXPECT_EQ(*result->data, expected[i]) << "frame " << i;
    }
    EXPECT_TRUE(session->Close().ok());
  }
}

TEST_F(RealServerTest, ReseedReplacesTheHistory) {
  const std::vector<GFrame> frames = MakeFrames(0, 6);
  const Image8 cut = Pattern8(kSide, kSide, 3, 4242);  // the keyframe after a camera cut
  // Frames 0..5 with a re-seed at frame 3.
  auto render_with_cut = [&](const SessionOptions& options) {
    std::unique_ptr<Session> session = Open(options);
    std::vector<std::string> pixels;
    if (session == nullptr) return pixels;
    for (const GFrame& frame : frames) {
      FrameRequest request = frame.request();
      if (frame.index == 3) request.keyframe = ImageView::Of(cut);
      absl::StatusOr<Frame> rendered = session->Render(request);
      ExpectFrame(rendered, frame.index);
      if (!rendered.ok()) return pixels;
      pixels.push_back(*rendered->data);
    }
    EXPECT_TRUE(session->Close().ok());
    return pixels;
  };

  const std::vector<std::string> plain = RenderSequence(Options(5), frames);
  const std::vector<std::string> reseeded = render_with_cut(Options(5));
  ASSERT_EQ(plain.size(), frames.size());
  ASSERT_EQ(reseeded.size(), frames.size());
  for (size_t i = 0; i < 3; ++i) EXPECT_EQ(reseeded[i], plain[i]) << "frame " << i;
  EXPECT_NE(reseeded[3], plain[3]);  // rendered from the keyframe, not frame 2
  EXPECT_NE(reseeded[3], reseeded[2]);

  // Another history (the session started from a keyframe, so frames 0..2
  // differ), the same seed and the same re-seed at the same frame counter:
  // from the cut on, the frames are the same — the re-seeded frame depends
  // only on the keyframe, its G-buffer and (seed, frame counter).
  const Image8 start = Pattern8(kSide, kSide, 3, 777);
  SessionOptions from_keyframe = Options(5);
  from_keyframe.keyframe = ImageView::Of(start);
  const std::vector<std::string> other = render_with_cut(from_keyframe);
  ASSERT_EQ(other.size(), frames.size());
  EXPECT_NE(other[0], reseeded[0]);
  for (size_t i = 3; i < frames.size(); ++i) EXPECT_EQ(other[i], reseeded[i]) << "frame " << i;
  // (A fresh session opened with `cut` as its keyframe would render frame 3
  // with the noise of frame counter 0, not 3, so it is not compared.)
}

TEST_F(RealServerTest, CloseEndsTheSessionOnTheServer) {
  std::unique_ptr<Session> session = Open(Options());
  ASSERT_NE(session, nullptr);
  const std::string id = session->session_id();
  ASSERT_EQ(RenderBlocking(session.get(), MakeFrames(0, 2)).size(), 2u);
  EXPECT_EQ(server_->store().live_sessions(), 1u);

  EXPECT_TRUE(session->Close().ok());
  EXPECT_EQ(srv::testing::AwaitSessionEnded(server_->store(), id),
            ::fd::session::EndReason::kClosed);
  EXPECT_EQ(server_->store().live_sessions(), 0u);
  EXPECT_EQ(session->Render(GFrame(2).request()).status().code(),
            absl::StatusCode::kFailedPrecondition);

  // The server refuses to resume it. (The SDK keeps the resume token to
  // itself, so the resume goes over the wire without it: PERMISSION_DENIED
  // comes first, before anything about the session is revealed.)
  namespace v1 = ::framediffuser::v1;
  srv::testing::StreamClient stream(srv::testing::Connect(*server_), {{"x-session-id", id}});
  ASSERT_TRUE(stream.Write(srv::testing::MakeResume(id, std::string(32, '0'))));
  std::vector<v1::RenderResponse> responses = stream.ReadAll();
  for (const v1::RenderResponse& response : responses) EXPECT_FALSE(response.has_opened());
  EXPECT_EQ(stream.Finish().error_code(), grpc::StatusCode::PERMISSION_DENIED);
  // And the store itself knows it only as closed.
  absl::StatusOr<std::shared_ptr<::fd::session::Session>> lookup = server_->store().Lookup(id);
  EXPECT_EQ(lookup.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(lookup.status().message(), HasSubstr("closed"));
}

TEST_F(RealServerTest, ErrorsCarryTheServersCodeAndMessage) {
  SessionOptions unknown = Options();
  unknown.environment = "atlantis";
  absl::StatusOr<std::unique_ptr<Session>> opened = client_->OpenSession(unknown);
  EXPECT_EQ(opened.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(opened.status().message(), HasSubstr("open.environment"));

  SessionOptions odd = Options();
  odd.width = 30;  // not a multiple of 8
  opened = client_->OpenSession(odd);
  EXPECT_EQ(opened.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(opened.status().message(), HasSubstr("open.width"));

  SessionOptions large = Options();
  large.height = 512;  // above the server's max_size 256
  opened = client_->OpenSession(large);
  EXPECT_EQ(opened.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(opened.status().message(), HasSubstr("open.height"));

  SessionOptions many_steps = Options();
  many_steps.steps = 9;  // above max_steps 8
  opened = client_->OpenSession(many_steps);
  EXPECT_EQ(opened.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(opened.status().message(), HasSubstr("open.steps"));
  EXPECT_EQ(server_->store().live_sessions(), 0u);

  // A frame the server rejects (FrameError) fails only that frame; the same
  // index may be sent again and the session goes on.
  SessionOptions client_sky = Options();
  client_sky.sky_mode = SkyMode::kClientImage;
  std::unique_ptr<Session> session = Open(client_sky);
  ASSERT_NE(session, nullptr);
  const GFrame frame(0);
  absl::StatusOr<Frame> rejected = session->Render(frame.request());
  EXPECT_EQ(rejected.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(rejected.status().message(), HasSubstr("frame.sky"));
  const Image8 sky = Pattern8(kSide, kSide, 3, 55);
  FrameRequest with_sky = frame.request();
  with_sky.sky = ImageView::Of(sky);
  ExpectFrame(session->Render(with_sky), 0);
  EXPECT_EQ(session->failover_count(), 0);
  EXPECT_TRUE(session->Close().ok());
}

// Server A drains (DRAINING notice, frames answered, stream ends UNAVAILABLE)
// and stops; server B starts on the same port. The SDK opens a new session
// on B from the last received frame and the sequence completes.
TEST_F(RealServerTest, FailoverAcrossAServerRestartOnTheSamePort) {
  const std::vector<GFrame> frames = MakeFrames(0, 12);
  const int port = server_->port();
  std::unique_ptr<Session> session = Open(Options(3));
  ASSERT_NE(session, nullptr);
  const std::string first_id = session->session_id();

  std::vector<absl::StatusOr<Frame>> results;
  for (const GFrame& frame : frames) {
    if (frame.index == 5) {
      server_->Shutdown();  // returns once A's streams have ended
      EXPECT_EQ(server_->store().live_sessions(), 0u);
      server_.reset();
      server_ = StartServer(absl::StrCat("127.0.0.1:", port));
      ASSERT_NE(server_, nullptr);
      ASSERT_EQ(server_->port(), port);
    }
    results.push_back(session->Render(frame.request()));
  }

  // Every index exactly once, in order.
  ASSERT_EQ(results.size(), frames.size());
  for (size_t i = 0; i < frames.size(); ++i) ExpectFrame(results[i], i);
  ASSERT_EQ(session->failover_count(), 1);
  ASSERT_EQ(events().size(), 1u);
  const FailoverEvent event = events()[0];
  EXPECT_FALSE(event.resumed);  // A drained: its sessions are gone
  EXPECT_EQ(event.cause.code(), absl::StatusCode::kUnavailable) << event.cause;
  EXPECT_THAT(event.cause.message(), HasSubstr("shutting down"));  // drained, not reset
  EXPECT_EQ(event.old_session_id, first_id);
  EXPECT_NE(event.new_session_id, first_id);
  EXPECT_EQ(session->session_id(), event.new_session_id);
  EXPECT_EQ(event.last_frame_index, std::optional<uint64_t>(4));
  EXPECT_LE(event.resent_frames, 1);  // frame 5, if it was sent before the break was seen
  EXPECT_EQ(server_->store().live_sessions(), 1u);  // the new session, on B
  const std::string second_id = session->session_id();
  EXPECT_TRUE(session->Close().ok());
  EXPECT_EQ(srv::testing::AwaitSessionEnded(server_->store(), second_id),
            ::fd::session::EndReason::kClosed);
  EXPECT_EQ(server_->store().live_sessions(), 0u);

  // Frames 0..4 are the uninterrupted chain's; frames 5..11 are what a fresh
  // session opened from frame 4 (its output and basecolor, the same seed)
  // renders — the noise restarts at frame counter 0 in the new session.
  std::vector<std::string> pixels;
  for (const absl::StatusOr<Frame>& result : results) pixels.push_back(*result->data);
  const std::vector<std::string> head = RenderSequence(Options(3), MakeFrames(0, 5));
  ASSERT_EQ(head.size(), 5u);
  for (size_t i = 0; i < 5; ++i) EXPECT_EQ(pixels[i], head[i]) << "frame " << i;
  SessionOptions continued = Options(3);
  continued.keyframe = ImageView::Raw(pixels[4].data(), kSide, kSide, 3, DType::kUint8);
  continued.keyframe_basecolor = ImageView::Of(frames[4].basecolor);
  const std::vector<std::string> tail = RenderSequence(continued, MakeFrames(5, 7));
  ASSERT_EQ(tail.size(), 7u);
  for (size_t i = 5; i < frames.size(); ++i) EXPECT_EQ(pixels[i], tail[i - 5]) << "frame " << i;
}

// As above with frames in flight when A starts draining: what A read is
// answered by A, the rest is sent again to B.
TEST_F(RealServerTest, FailoverWithFramesInFlight) {
  const std::vector<GFrame> frames = MakeFrames(0, 12);
  const int port = server_->port();
  std::unique_ptr<Session> session = Open(Options(3));
  ASSERT_NE(session, nullptr);
  ResultLog log;
  std::promise<void> reached;
  for (const GFrame& frame : frames) {
    ASSERT_TRUE(session
                    ->Submit(frame.request(),
                             [&, index = frame.index](absl::StatusOr<Frame> result) {
                               log.Add(std::move(result), index);
                               if (index == 4) reached.set_value();
                             })
                    .ok());
    if (frame.index == 6) {
      reached.get_future().wait();
      server_->Shutdown();
      server_.reset();
      server_ = StartServer(absl::StrCat("127.0.0.1:", port));
      ASSERT_NE(server_, nullptr);
      ASSERT_EQ(server_->port(), port);
    }
  }
  ASSERT_TRUE(log.WaitFor(frames.size()));
  const std::vector<absl::StatusOr<Frame>> results = log.results();
  ASSERT_EQ(results.size(), frames.size());
  for (size_t i = 0; i < frames.size(); ++i) {
    EXPECT_EQ(log.indices()[i], i);
    ExpectFrame(results[i], i);
  }
  EXPECT_EQ(session->failover_count(), 1);
  ASSERT_EQ(events().size(), 1u);
  EXPECT_FALSE(events()[0].resumed);
  const std::string second_id = session->session_id();
  EXPECT_TRUE(session->Close().ok());
  EXPECT_EQ(srv::testing::AwaitSessionEnded(server_->store(), second_id),
            ::fd::session::EndReason::kClosed);
  EXPECT_EQ(server_->store().live_sessions(), 0u);
}

// The connection breaks but the server keeps the session: the SDK resumes
// it (same id, same server) and the chain continues bit for bit.
TEST_F(RealServerTest, ResumeAfterABrokenConnectionContinuesTheChain) {
  const std::vector<GFrame> frames = MakeFrames(0, 10);
  const std::vector<std::string> expected = RenderSequence(Options(9), frames);
  ASSERT_EQ(expected.size(), frames.size());

  TcpForwarder forwarder(server_->port());
  ASSERT_TRUE(forwarder.ok());
  std::unique_ptr<Client> client = MakeClient(forwarder.address());
  ASSERT_NE(client, nullptr);
  std::unique_ptr<Session> session = Open(Options(9), client.get());
  ASSERT_NE(session, nullptr);
  const std::string id = session->session_id();

  std::vector<std::string> pixels = RenderBlocking(session.get(), MakeFrames(0, 5));
  ASSERT_EQ(pixels.size(), 5u);
  forwarder.BreakAll();
  const std::vector<std::string> rest = RenderBlocking(session.get(), MakeFrames(5, 5));
  ASSERT_EQ(rest.size(), 5u);
  pixels.insert(pixels.end(), rest.begin(), rest.end());
  EXPECT_EQ(pixels, expected);

  EXPECT_EQ(session->failover_count(), 1);
  ASSERT_EQ(events().size(), 1u);
  EXPECT_TRUE(events()[0].resumed);
  EXPECT_EQ(events()[0].old_session_id, id);
  EXPECT_EQ(events()[0].new_session_id, id);
  EXPECT_EQ(events()[0].last_frame_index, std::optional<uint64_t>(4));
  EXPECT_EQ(session->session_id(), id);
  EXPECT_GE(forwarder.connections(), 2);
  EXPECT_TRUE(session->Close().ok());
  EXPECT_EQ(srv::testing::AwaitSessionEnded(server_->store(), id),
            ::fd::session::EndReason::kClosed);
  EXPECT_EQ(server_->store().live_sessions(), 0u);
}

}  // namespace
}  // namespace fd::client

// Helpers for the in-process server tests: the tiny environment (built once
// per test binary), a test config on port 0, wire images and a blocking
// Render stream client.
#ifndef FD_TESTS_SERVER_SERVER_TEST_UTIL_H_
#define FD_TESTS_SERVER_SERVER_TEST_UTIL_H_

#include <grpcpp/grpcpp.h>

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/synchronization/notification.h"
#include "absl/time/clock.h"
#include "framediffuser/v1/render_service.grpc.pb.h"
#include "gtest/gtest.h"
#include "server/embedded_environment.h"
#include "server/log.h"
#include "server/server.h"
#include "server/server_config.h"
#include "session/random_environment.h"
#include "tests/testing/scripted_frame_pipeline.h"

namespace fd::server::testing {

namespace v1 = ::framediffuser::v1;

// The random tiny test environment (session/random_environment.h), loaded
// once and shared (models are immutable).
inline std::shared_ptr<const model::Environment> TinyEnvironment() {
  static const std::shared_ptr<const model::Environment> env = [] {
    absl::StatusOr<std::shared_ptr<model::Environment>> created =
        session::CreateRandomTinyEnvironment(model::EnvironmentOptions{});
    EXPECT_TRUE(created.ok()) << created.status();
    return created.ok() ? std::shared_ptr<const model::Environment>(*created) : nullptr;
  }();
  return env;
}

// Small, fast sessions: 32x32 frames, 2 steps.
inline constexpr uint32_t kSize = 32;
inline constexpr uint32_t kSteps = 2;

inline ServerConfig TestConfig() {
  ServerConfig config;
  config.listen = "127.0.0.1:0";
  config.min_size = 16;
  config.max_size = 256;
  config.max_steps = 8;
  config.max_queue_delay = absl::ZeroDuration();
  config.reaper_interval = absl::Hours(24);  // tests expire explicitly
  config.drain_timeout = absl::Seconds(60);
  config.log_format = "json";
  return config;
}

// A uint8 image with a deterministic pattern that depends on `salt`.
inline v1::Image MakeImage(uint32_t width, uint32_t height, uint32_t channels, int salt = 0) {
  v1::Image image;
  image.set_width(width);
  image.set_height(height);
  image.set_channels(channels);
  image.set_dtype(v1::DTYPE_UINT8);
  std::string data(static_cast<size_t>(width) * height * channels, '\0');
  for (size_t i = 0; i < data.size(); ++i) {
    data[i] = static_cast<char>((i * 37 + static_cast<size_t>(salt) * 11) % 251);
  }
  image.set_data(std::move(data));
  return image;
}

inline v1::RenderRequest MakeFrame(uint64_t index, uint32_t width = kSize,
                                   uint32_t height = kSize) {
  v1::RenderRequest request;
  v1::FrameInput* frame = request.mutable_frame();
  frame->set_frame_index(index);
  const int salt = static_cast<int>(index);
  *frame->mutable_gbuffer()->mutable_basecolor() = MakeImage(width, height, 3, salt);
  *frame->mutable_gbuffer()->mutable_normals() = MakeImage(width, height, 3, salt + 1);
  *frame->mutable_gbuffer()->mutable_depth() = MakeImage(width, height, 1, salt + 2);
  *frame->mutable_gbuffer()->mutable_roughness() = MakeImage(width, height, 1, salt + 3);
  return request;
}

inline v1::RenderRequest MakeOpen(const std::string& environment = kEmbeddedEnvironmentName,
                                  uint64_t seed = 7) {
  v1::RenderRequest request;
  v1::OpenSession* open = request.mutable_open();
  open->set_environment(environment);
  open->set_width(kSize);
  open->set_height(kSize);
  open->set_steps(kSteps);
  open->set_seed(seed);
  return request;
}

inline v1::RenderRequest MakeResume(const std::string& id, const std::string& token) {
  v1::RenderRequest request;
  request.mutable_resume()->set_session_id(id);
  request.mutable_resume()->set_resume_token(token);
  return request;
}

// One blocking Render stream.
class StreamClient {
 public:
  explicit StreamClient(std::shared_ptr<grpc::Channel> channel,
                        std::vector<std::pair<std::string, std::string>> metadata = {})
      : stub_(v1::FrameDiffuser::NewStub(std::move(channel))) {
    for (const auto& [key, value] : metadata) context_.AddMetadata(key, value);
    stream_ = stub_->Render(&context_);
  }

  bool Write(const v1::RenderRequest& request) { return stream_->Write(request); }
  void WritesDone() { stream_->WritesDone(); }
  // The next response; nullopt at the end of the stream.
  std::optional<v1::RenderResponse> Read() {
    v1::RenderResponse response;
    if (!stream_->Read(&response)) return std::nullopt;
    return response;
  }
  // Reads to the end; returns the remaining responses.
  std::vector<v1::RenderResponse> ReadAll() {
    std::vector<v1::RenderResponse> responses;
    while (std::optional<v1::RenderResponse> r = Read()) responses.push_back(*std::move(r));
    return responses;
  }
  grpc::Status Finish() { return stream_->Finish(); }
  void Cancel() { context_.TryCancel(); }

 private:
  std::unique_ptr<v1::FrameDiffuser::Stub> stub_;
  grpc::ClientContext context_;
  std::unique_ptr<grpc::ClientReaderWriter<v1::RenderRequest, v1::RenderResponse>> stream_;
};

// Starts a server; on failure records the error and returns nullptr.
inline std::unique_ptr<FrameDiffuserServer> StartOrNull(ServerOptions options) {
  absl::StatusOr<std::unique_ptr<FrameDiffuserServer>> server =
      FrameDiffuserServer::Start(std::move(options));
  EXPECT_TRUE(server.ok()) << server.status();
  return server.ok() ? *std::move(server) : nullptr;
}

// The real pipeline, except that the scheduler's denoising step call number
// `gated_call` (0-based, counted over the whole server) notifies `stepping`
// and then blocks until `gate` opens: a frame is then provably in flight.
// Call 0 is a first step (a cancel drops the frame at the next boundary);
// call kSteps - 1 is the first frame's last step (no boundary is left: the
// frame completes even if cancelled meanwhile).
inline session::PipelineFactory GatedStep(std::shared_ptr<fd::testing::Gate> gate,
                                          std::shared_ptr<absl::Notification> stepping,
                                          int gated_call) {
  return [gate, stepping, gated_call](std::shared_ptr<const model::Environment> env) {
    auto pipeline = std::make_unique<fd::testing::ScriptedFramePipeline>(
        std::make_shared<session::ModelFramePipeline>(env));
    pipeline->before_step = [gate, stepping, gated_call](int call, size_t) {
      if (call == gated_call) {
        stepping->Notify();
        gate->Wait();
      }
    };
    return pipeline;
  };
}

inline session::PipelineFactory GatedFirstStep(std::shared_ptr<fd::testing::Gate> gate,
                                               std::shared_ptr<absl::Notification> stepping) {
  return GatedStep(std::move(gate), std::move(stepping), /*gated_call=*/0);
}

// Spins (yielding) until `done()` holds; false after 60 s, so that a state
// that never comes fails the test instead of hanging it.
template <typename Predicate>
bool AwaitTrue(Predicate done) {
  const absl::Time give_up = absl::Now() + absl::Seconds(60);
  while (!done()) {
    if (absl::Now() > give_up) return false;
    std::this_thread::yield();
  }
  return true;
}

// A half-close closes its session when the server's call completes, just
// after the client saw the OK status (StreamController::Detach): waits for
// the store to say the session ended, then returns why.
inline std::optional<session::EndReason> AwaitSessionEnded(const session::SessionStore& store,
                                                           const std::string& session_id) {
  if (!AwaitTrue([&] { return store.EndReasonOf(session_id).has_value(); })) {
    ADD_FAILURE() << "session " << session_id << " did not end";
  }
  return store.EndReasonOf(session_id);
}

// Waits until a captured log line contains `needle` (e.g. the session_close
// event, written just after the store ends the session).
inline bool AwaitLogLine(const ScopedLogCapture& logs, const std::string& needle) {
  return AwaitTrue([&] {
    for (const std::string& line : logs.lines()) {
      if (line.find(needle) != std::string::npos) return true;
    }
    return false;
  });
}

inline std::shared_ptr<grpc::Channel> Connect(const FrameDiffuserServer& server) {
  grpc::ChannelArguments args;
  args.SetMaxReceiveMessageSize(-1);
  args.SetMaxSendMessageSize(-1);
  return grpc::CreateCustomChannel(server.address(), grpc::InsecureChannelCredentials(), args);
}

}  // namespace fd::server::testing

#endif  // FD_TESTS_SERVER_SERVER_TEST_UTIL_H_

// Shared pieces of the SDK tests: a FakeRenderServer on 127.0.0.1:0, a
// client for it, deterministic G-buffer frames, and the outputs the fake's
// model must produce for them (computed here from the formula, not by the
// SDK).
#ifndef FD_TESTS_CLIENT_SDK_SDK_FIXTURE_H_
#define FD_TESTS_CLIENT_SDK_SDK_FIXTURE_H_

#include <gtest/gtest.h>

#include <condition_variable>
#include <memory>
#include <mutex>
#include <vector>

#include "client_sdk/client.h"
#include "tests/client_sdk/test_util.h"
#include "tests/testing/fake_render_server.h"

namespace fd::client::testing {

inline constexpr int kSize = 16;  // the fake's native size

// The G-buffer of frame i (pixels owned here; FrameRequest holds views).
struct TestFrame {
  uint64_t index = 0;
  Image8 basecolor, normals, depth, roughness;

  explicit TestFrame(uint64_t i)
      : index(i),
        basecolor(Pattern8(kSize, kSize, 3, 100 + int(i))),
        normals(Pattern8(kSize, kSize, 3, 200 + int(i))),
        depth(Pattern8(kSize, kSize, 1, 300 + int(i))),
        roughness(Pattern8(kSize, kSize, 1, 400 + int(i))) {}

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

inline std::vector<TestFrame> MakeFrames(int count) {
  std::vector<TestFrame> frames;
  for (int i = 0; i < count; ++i) frames.emplace_back(i);
  return frames;
}

// Output of the fake model for `frame` given the previous output, quantised
// to uint8 as the session's default output dtype.
inline Image8 ExpectedOutput(const TestFrame& frame, const Image8& previous) {
  const ImageF prev = previous.empty() ? ImageF() : ToFloat(ImageView::Of(previous));
  return ToUint8(ImageView::Of(fd::testing::FakeRenderServer::Render(
      ToFloat(ImageView::Of(frame.basecolor)), ToFloat(ImageView::Of(frame.depth)), prev)));
}

// The whole sequence rendered without interruption, from `keyframe`.
inline std::vector<Image8> ExpectedSequence(const std::vector<TestFrame>& frames,
                                            const Image8& keyframe = Image8()) {
  std::vector<Image8> outputs;
  Image8 previous = keyframe;
  for (const TestFrame& frame : frames) {
    outputs.push_back(ExpectedOutput(frame, previous));
    previous = outputs.back();
  }
  return outputs;
}

// Collects asynchronous results and lets a test wait for a count of them.
class ResultLog {
 public:
  void Add(absl::StatusOr<Frame> result, uint64_t submitted_index) {
    std::lock_guard<std::mutex> lock(mu_);
    results_.push_back(std::move(result));
    indices_.push_back(submitted_index);
    cv_.notify_all();
  }
  // Waits for `count` results (the SDK guarantees completion or failure,
  // so this returns; the generous bound only protects the test run).
  bool WaitFor(size_t count) {
    std::unique_lock<std::mutex> lock(mu_);
    return cv_.wait_for(lock, std::chrono::seconds(60), [&] { return results_.size() >= count; });
  }
  std::vector<absl::StatusOr<Frame>> results() {
    std::lock_guard<std::mutex> lock(mu_);
    return results_;
  }
  std::vector<uint64_t> indices() {
    std::lock_guard<std::mutex> lock(mu_);
    return indices_;
  }

 private:
  std::mutex mu_;
  std::condition_variable cv_;
  std::vector<absl::StatusOr<Frame>> results_;
  std::vector<uint64_t> indices_;
};

class SdkTest : public ::testing::Test {
 protected:
  void SetUp() override { StartServer({}); }

  void StartServer(fd::testing::FakeRenderServerOptions options) {
    server_ = std::make_unique<fd::testing::FakeRenderServer>(std::move(options));
    ASSERT_TRUE(server_->Start().ok());
    client_ = MakeClient();
  }

  std::unique_ptr<Client> MakeClient(const std::string& token = "") {
    ClientOptions options;
    options.target = server_->address();
    options.bearer_token = token;
    options.max_reconnect_backoff = absl::Milliseconds(100);
    absl::StatusOr<std::unique_ptr<Client>> client = Client::Create(options);
    EXPECT_TRUE(client.ok()) << client.status();
    return client.ok() ? std::move(*client) : nullptr;
  }

  SessionOptions DefaultSessionOptions() const {
    SessionOptions options;
    options.environment = "tiny";
    options.seed = 7;
    options.failover_timeout = absl::Seconds(20);
    return options;
  }

  std::unique_ptr<Session> Open(const SessionOptions& options) {
    absl::StatusOr<std::unique_ptr<Session>> session = client_->OpenSession(options);
    EXPECT_TRUE(session.ok()) << session.status();
    return session.ok() ? std::move(*session) : nullptr;
  }

  std::unique_ptr<fd::testing::FakeRenderServer> server_;
  std::unique_ptr<Client> client_;
};

}  // namespace fd::client::testing

#endif  // FD_TESTS_CLIENT_SDK_SDK_FIXTURE_H_

// FakeRenderServer: a minimal, in-process stand-in for framediffuser-server,
// for testing the C++ SDK (client_sdk/) until the real server (issue 7)
// exists; integration tests will then run against the real one.
//
// It implements the wire contract of render_service.proto with a trivial
// deterministic "model" instead of FrameDiffuser:
//   output = clamp((2 * basecolor + previous + depth) / 4), per RGB channel,
// where `previous` is the session's previous output (or its keyframe, zeros
// at first), quantised to the session's output dtype. Because the output
// depends on the previous one, a test can tell whether a sequence continued
// from the right frame (e.g. after failover).
//
// Served on 127.0.0.1 with a port picked by the OS at the first Start();
// Stop() + Start() restarts on the same port (a "server restart"). Sessions
// are dropped on Stop unless keep_sessions_across_restart. Also registers
// gRPC's standard health service. Test hooks break streams at chosen points;
// nothing waits on wall-clock time.
#ifndef FD_TESTS_TESTING_FAKE_RENDER_SERVER_H_
#define FD_TESTS_TESTING_FAKE_RENDER_SERVER_H_

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/time/time.h"
#include "client_sdk/image.h"

namespace fd::testing {

struct FakeRenderServerOptions {
  std::vector<std::string> environments = {"tiny"};
  uint32_t native_size = 16;  // native width and height
  uint32_t min_size = 8;
  uint32_t max_size = 64;
  uint32_t default_steps = 4;
  uint32_t max_steps = 8;
  // Server-side cap on a session's max_frames_in_flight (and its default).
  uint32_t max_frames_in_flight = 4;
  // When set, every call needs "authorization: Bearer <token>".
  std::string required_token;
  bool keep_sessions_across_restart = false;
  // TLS when both are set (PEM).
  std::string tls_cert_pem;
  std::string tls_key_pem;
};

class FakeRenderServer {
 public:
  explicit FakeRenderServer(FakeRenderServerOptions options = {});
  ~FakeRenderServer();
  FakeRenderServer(const FakeRenderServer&) = delete;
  FakeRenderServer& operator=(const FakeRenderServer&) = delete;

  // Starts serving: on a fresh port the first time, on the same port after
  // Stop(). INTERNAL when the port cannot be bound.
  absl::Status Start();
  // Shuts down at once: open streams are cancelled (clients see the stream
  // break). Idempotent.
  void Stop();
  int port() const;
  std::string address() const;  // "127.0.0.1:<port>"
  // Makes the next Start() bind `port` instead of a free one (0 = any).
  void SetPortForTesting(int port);

  // ---- Test hooks (thread-safe) ----
  // Ends every open stream with UNAVAILABLE; sessions stay resumable.
  void BreakStreams();
  // Sends a DRAINING notice on every open stream, ends them with UNAVAILABLE
  // and forgets every session (resume then fails), like a draining server.
  void Drain();
  enum class BreakPoint {
    kBeforeRender,  // the frame is dropped unrendered
    kAfterRender,   // rendered (the session advances) but never answered
  };
  // The next time frame `frame_index` arrives, its stream ends with
  // UNAVAILABLE at `point`. One-shot.
  void BreakOnFrame(uint64_t frame_index, BreakPoint point);
  // Makes the next open fail with `code` and `message` (stream-level). One-shot.
  void FailNextOpen(int code, const std::string& message);
  // While paused, frames are read (up to the session's frames in flight)
  // but not rendered; Resume renders them in order.
  void PauseRendering();
  void ResumeRendering();
  // Waits until `count` frames have been received in total since
  // construction; false if `timeout` passes first (a safety net only).
  bool WaitForFramesReceived(int count, absl::Duration timeout);

  // ---- Observations ----
  int sessions_opened() const;
  int sessions_resumed() const;
  int frames_received() const;
  int frames_rendered() const;
  // Largest number of frames one stream had read but not yet answered.
  int max_outstanding_frames() const;
  // x-session-id metadata of every Render call, in arrival order ("" if
  // absent), and the session ids handed out.
  std::vector<std::string> x_session_id_headers() const;
  std::vector<std::string> opened_session_ids() const;
  // authorization metadata of every call.
  std::vector<std::string> authorization_headers() const;

  // The fake model (see above) on float images in [0, 1]: basecolor and
  // previous RGB, depth 1 channel; an empty `previous` means zeros.
  static client::ImageF Render(const client::ImageF& basecolor, const client::ImageF& depth,
                               const client::ImageF& previous);

  struct State;  // shared with the service and its reactors

 private:
  std::shared_ptr<State> state_;
};

}  // namespace fd::testing

#endif  // FD_TESTS_TESTING_FAKE_RENDER_SERVER_H_

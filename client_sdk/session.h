// A FrameDiffuser render session: one autoregressive frame sequence on the
// server (one bidirectional gRPC stream), opened with Client::OpenSession.
//
//   fd::client::SessionOptions options;
//   options.environment = "tiny";
//   options.keyframe = fd::client::ImageView::Of(first_ground_truth);  // optional
//   auto session = client->OpenSession(options);              // StatusOr
//   for (uint64_t i = 0;; ++i) {
//     fd::client::FrameRequest frame;
//     frame.frame_index = i;
//     frame.gbuffer.basecolor = fd::client::ImageView::Raw(ptr, w, h, 4, DType::kUint8);
//     ...                                                      // normals, depth, roughness
//     absl::StatusOr<fd::client::Frame> lit = (*session)->Render(frame);  // blocking
//   }
//
// Pipelining. The server renders one frame of a session at a time, in order,
// each from the previous output. Submit()/RenderAsync() return as soon as the
// frame is uploaded, so frame N+1 travels while frame N renders; at most
// frames_in_flight() frames are outstanding (Submit blocks for a slot), so
// the client never runs ahead of the server's flow control.
//
// Failover (SessionOptions::failover, on by default). When the stream breaks
// (server restart, node loss behind a load balancer, draining), the session
// re-attaches with ResumeSession (sending x-session-id so a sticky balancer
// finds the server) if that server still holds it with no rendered frame
// lost; otherwise it opens a new session on the same target with the last
// received frame as keyframe (its basecolor as keyframe_basecolor) and the
// same settings and seed, then re-sends every unanswered frame. Callers see
// every frame exactly once, in order; each failover is reported to
// SessionOptions::on_failover and counted. A resume continues the chain bit
// for bit. A re-open continues it visually (same previous frame) but not bit
// for bit: the new session's noise counter starts again at 0, so frames after
// the break differ from an uninterrupted run's.
//
// Errors are absl::Status with the server's gRPC code and message. A frame
// the server rejects (FrameError) fails only that frame; the session goes on.
// A stream-level error that failover cannot fix fails every outstanding frame
// and the session (later calls return that status).
//
// Thread-safety: all methods are thread-safe. Callbacks run on the session's
// receiver thread, one at a time, in frame order; they may call Submit but
// must not block for long and must not call Render(), Close() or destroy the
// session (each waits for the receiver thread).
#ifndef FD_CLIENT_SDK_SESSION_H_
#define FD_CLIENT_SDK_SESSION_H_

#include <cstdint>
#include <functional>
#include <future>
#include <memory>
#include <optional>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/time/time.h"
#include "client_sdk/image.h"

namespace fd::client {

// Mirrors of the wire enums (render_service.proto); kDefault = the
// environment's default.
enum class Scheduler { kDefault, kUniPC, kDpmSolverPP2M, kDdim, kEuler };
enum class SkyMode { kDefault, kClientImage, kPreviousOutput, kOff };
enum class Compression { kNone, kZstd };

// One frame's G-buffer. Views of caller memory: copied once into the request
// by Submit/Render, so the memory may be reused when they return. Sizes must
// equal the session's width x height. Colour fields take 3 channels or 4
// (alpha dropped while copying); scalar fields take 1 channel, or use
// ImageView::select_channel to pick one from a packed texture. Values in
// [0, 1] (uint8 0..255), normals as n * 0.5 + 0.5.
struct GBuffer {
  ImageView basecolor;  // required
  ImageView normals;    // required
  ImageView depth;      // required; 0 = sky (e.g. inverse depth near / d)
  ImageView roughness;  // required
  ImageView metallic;   // optional: empty = all zeros
};

struct FrameRequest {
  // Strictly greater than the previous frame's (gaps allowed); a frame the
  // server rejected (FrameError) may be retried with the same index.
  uint64_t frame_index = 0;
  GBuffer gbuffer;
  // Sky RGB; required when the session's sky mode is kClientImage.
  ImageView sky;
  // Re-seed (e.g. after a camera cut): render this frame from `keyframe`
  // (RGB) instead of the previous output. keyframe_basecolor defaults to this
  // frame's basecolor.
  ImageView keyframe;
  ImageView keyframe_basecolor;
};

// Time the server spent on one frame (RenderedFrame.timings).
struct StageTimings {
  double queue_ms = 0, encode_ms = 0, denoise_ms = 0, decode_ms = 0, total_ms = 0;
  uint32_t batch_size = 0;
};

// A rendered frame: 3-channel RGB in the session's output dtype. The pixels
// are the bytes the server sent (moved out of the response, decompressed if
// needed), shared and immutable, so copying a Frame is cheap.
struct Frame {
  uint64_t frame_index = 0;
  int width = 0;
  int height = 0;
  int channels = 0;
  DType dtype = DType::kUint8;
  std::shared_ptr<const std::string> data;  // width * height * channels elements
  StageTimings timings;

  ImageView view() const;
  Image8 ToImage8() const { return ToUint8(view()); }
  ImageF ToFloat() const { return fd::client::ToFloat(view()); }
  AnyImage ToImage() const { return ConvertTo(view(), dtype); }
};

// Settings in effect, after the server applied its defaults.
struct SessionSettings {
  std::string environment;
  uint32_t width = 0;
  uint32_t height = 0;
  uint64_t seed = 0;
  uint32_t steps = 0;
  Scheduler scheduler = Scheduler::kDefault;
  SkyMode sky_mode = SkyMode::kDefault;
  DType output_dtype = DType::kUint8;
  Compression output_compression = Compression::kNone;
  uint32_t max_frames_in_flight = 0;
  bool started_from_keyframe = false;
};

// One failover, as reported to SessionOptions::on_failover.
struct FailoverEvent {
  absl::Status cause;          // why the stream broke
  bool resumed = false;        // true: the same session re-attached
  std::string old_session_id;  // before
  std::string new_session_id;  // after (equal when resumed)
  // Last frame the caller received before the break (nullopt: none yet);
  // the new session starts from it.
  std::optional<uint64_t> last_frame_index;
  int resent_frames = 0;  // unanswered frames sent again
};

struct SessionOptions {
  // Environment name from ListEnvironments. Required.
  std::string environment;
  // Frame size; 0 = the environment's native size.
  uint32_t width = 0;
  uint32_t height = 0;
  // 0 = the server picks (reported in settings()).
  uint64_t seed = 0;
  uint32_t steps = 0;  // 0 = environment default
  Scheduler scheduler = Scheduler::kDefault;
  SkyMode sky_mode = SkyMode::kDefault;
  // The "previous frame" of the first frame (RGB), and its basecolor.
  // Copied by OpenSession (and kept for failover before the first frame).
  ImageView keyframe;
  ImageView keyframe_basecolor;
  DType output_dtype = DType::kUint8;
  Compression output_compression = Compression::kNone;
  // zstd-compress uploaded images (saves bandwidth on slow links).
  Compression input_compression = Compression::kNone;
  int zstd_level = 1;
  // Frames outstanding at once; the server may lower it (settings()).
  uint32_t max_frames_in_flight = 2;
  // Transparent failover (see above).
  bool failover = true;
  // Give up a failover (and fail the session) after this long.
  absl::Duration failover_timeout = absl::Seconds(30);
  // Called on the receiver thread after each successful failover.
  std::function<void(const FailoverEvent&)> on_failover;
  // Bound on opening the session (connect + SessionOpened).
  absl::Duration open_timeout = absl::Seconds(30);
};

class SessionImpl;

class Session {
 public:
  using FrameCallback = std::function<void(absl::StatusOr<Frame>)>;

  // Cancels the stream without waiting: frames still outstanding complete
  // with CANCELLED. Call Close() first for a clean end.
  ~Session();
  Session(const Session&) = delete;
  Session& operator=(const Session&) = delete;

  // Current session id (changes when failover opens a new session).
  std::string session_id() const;
  SessionSettings settings() const;
  // Frames this session may have outstanding (min of the requested and the
  // server's limit, at least 1).
  uint32_t frames_in_flight() const;
  // Failovers so far.
  int failover_count() const;

  // Uploads one frame and blocks until it is rendered. Returns the frame,
  // the FrameError's status (e.g. INVALID_ARGUMENT naming the field) or the
  // session's failure.
  absl::StatusOr<Frame> Render(const FrameRequest& request);

  // Uploads one frame and returns once it is handed to the stream (blocking
  // while frames_in_flight() frames are outstanding). On OK, `done` is called
  // exactly once with the frame or its error. Errors returned here (and then
  // `done` is not called): INVALID_ARGUMENT for a bad image (naming the
  // field), FAILED_PRECONDITION for a frame_index not above the last rendered
  // or outstanding frame's (a frame the server rejected may be sent again
  // with its index) or a closed session, or the session's failure status.
  absl::Status Submit(const FrameRequest& request, FrameCallback done);

  // Submit with a future; a Submit error is delivered through the future.
  std::future<absl::StatusOr<Frame>> RenderAsync(const FrameRequest& request);

  // Waits until every submitted frame is answered, half-closes the stream
  // (which closes the session on the server) and returns the stream's final
  // status (OK, or why the session failed). Idempotent.
  absl::Status Close();

 private:
  friend class Client;
  explicit Session(std::unique_ptr<SessionImpl> impl);
  std::unique_ptr<SessionImpl> impl_;
};

}  // namespace fd::client

#endif  // FD_CLIENT_SDK_SESSION_H_

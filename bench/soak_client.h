// One soak client (bench/soak.cc): a thread that drives Render streams
// through the generated stubs (no SDK, so that it sees the raw stream and
// can check every answer's place in it) and mixes what real clients do:
// normal streaming, slow reading, invalid frames, cancel + resume, reconnects
// on a new channel, takeovers and session churn. It records what every
// session rendered, so that the session can be replayed alone afterwards
// (ReplaySession) and compared bit for bit.
//
// What it checks on the wire, for every session:
//  - each frame written gets exactly one answer, in write order (the frame
//    itself, or a FrameError for the frames it made invalid on purpose; a
//    valid frame never gets a FrameError);
//  - after a broken stream, ResumeSession answers with a last_frame_index
//    that covers every frame already answered and names a frame it sent; the
//    frames up to it count as rendered (their answers were lost with the
//    stream, as the proto says), the valid frames after it are sent again, so
//    no accepted frame is lost;
//  - a half-close answers every frame still in flight and ends with OK; a
//    closed session cannot be resumed (notice CLOSED, NOT_FOUND).
#ifndef FD_BENCH_SOAK_CLIENT_H_
#define FD_BENCH_SOAK_CLIENT_H_

#include <grpcpp/grpcpp.h>

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/time/time.h"
#include "framediffuser/v1/render_service.grpc.pb.h"

namespace fd::bench {

namespace v1 = ::framediffuser::v1;

struct SoakClientOptions {
  std::string target;                 // host:port of the server
  std::string environment;            // served environment name
  uint32_t size = 32;                 // frame width and height
  uint32_t steps = 2;                 // denoising steps per frame
  uint32_t max_frames_in_flight = 4;  // the server's cap; sessions pick 1..this
  uint64_t run_seed = 1;              // everything random in a run derives from it
  absl::Time deadline;                // no new behaviour starts after it
};

// A frame the session rendered, in rendering order.
struct RenderedFrame {
  uint64_t frame_index = 0;
  uint64_t input_seed = 0;  // MakeFrame's seed: the G-buffer can be made again
  // FNV-1a of the answer's image data; empty when the answer was lost with a
  // broken stream (the frame still counts: the resume said so).
  std::optional<uint64_t> hash;
};

// What one session did, for the replay.
struct SessionRecord {
  std::string session_id;
  int client = 0;
  uint64_t seed = 0;
  std::vector<RenderedFrame> rendered;
};

struct ClientCounts {
  int64_t sessions_opened = 0;
  int64_t sessions_closed = 0;       // half-closed, every answer received, OK
  int64_t frames_written = 0;        // every frame message, invalid and re-sent ones included
  int64_t frames_answered = 0;       // RenderedFrame answers
  int64_t frame_errors = 0;          // FrameError answers (all to invalid frames)
  int64_t answers_lost = 0;          // rendered frames whose answer went with a broken stream
  int64_t frames_resent = 0;         // valid frames sent again after a resume
  int64_t cancels = 0;               // streams cancelled, then resumed on the same channel
  int64_t reconnects = 0;            // streams cancelled, then resumed on a new channel
  int64_t takeovers = 0;             // resumed on a second stream while the first was open
  int64_t slow_segments = 0;         // stretches of slow reading
  int64_t closed_resume_checks = 0;  // resumes of a closed session, refused as they must be

  void Add(const ClientCounts& other);
};

struct ClientResult {
  std::vector<SessionRecord> sessions;
  ClientCounts counts;
  std::vector<double> latency_ms;  // write to answer, frames of normal segments
  std::string failure;             // empty: every check held
};

// Runs client `client` until options.deadline, then closes its session.
// Stops at the first failed check (ClientResult::failure says which).
ClientResult RunSoakClient(int client, const SoakClientOptions& options);

// A channel with its own TCP connection (no subchannel sharing), unlimited
// message sizes.
std::shared_ptr<grpc::Channel> NewChannel(const std::string& target);

// Renders `record`'s frames again in a fresh session with the same seed on
// `channel`, nothing else running, and compares every hash it has. OK, or
// the first difference or error.
absl::Status ReplaySession(const std::shared_ptr<grpc::Channel>& channel,
                           const SoakClientOptions& options, const SessionRecord& record,
                           int64_t* frames_compared);

}  // namespace fd::bench

#endif  // FD_BENCH_SOAK_CLIENT_H_

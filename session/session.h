// One client's session: its autoregressive state plus the bookkeeping that
// keeps at most one frame in flight and frame indices strictly increasing.
//
// Frame protocol (server and frame batcher):
//   1. TryBeginFrame(frame_index[, keyframe])  — claims the session for one
//      frame; a keyframe re-seeds the chain for this frame (camera cut).
//   2. ReadFrameContext(frame_index, fn)       — the pipeline reads the
//      previous frame/basecolor and the frame's noise seed.
//   3. CommitFrame(frame_index, output, basecolor) on success, or
//      AbortFrame(frame_index) on failure or cancellation. An aborted frame
//      leaves the state exactly as before (the wire API: a rejected frame does
//      not become the "previous" frame; the client may retry that index, and
//      it gets the same noise because the frame counter did not move).
//
// Sessions are shared: the store holds one reference while the session is
// live, and whoever works on a frame holds another, so a frame in flight
// keeps its session alive after the store ended it. Ending is a flag
// (end_reason()) the scheduler polls to cancel work.
#ifndef FD_SESSION_SESSION_H_
#define FD_SESSION_SESSION_H_

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/functional/function_ref.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "absl/types/span.h"
#include "base/image_buffer.h"
#include "session/clock.h"
#include "session/end_reason.h"
#include "session/session_state.h"

namespace fd::session {

// A client keyframe that re-seeds the chain (FrameInput.keyframe /
// keyframe_basecolor): uint8 HWC RGB of the session's size; an empty
// basecolor means "this frame's own basecolor".
struct Keyframe {
  ImageBuffer frame;
  ImageBuffer basecolor;
};

// What the frame in flight is conditioned on. The images share the
// session's immutable buffers, so they stay valid after the callback.
struct FrameContext {
  uint64_t frame_index = 0;
  // 0-based number of this frame in the session; FrameSeed(seed, it) = seed.
  uint64_t frame_counter = 0;
  // Seed of this frame's noise/VAE generator (frame_seed.h).
  uint64_t frame_seed = 0;
  // The "previous frame" (last output, start keyframe or re-seed keyframe),
  // uint8 HWC RGB; empty: none yet (black irradiance, zero previous latent).
  ImageBuffer previous_frame;
  // Basecolor for the irradiance estimate; empty: this frame's own basecolor
  // (keyframe without a basecolor), or no previous frame at all.
  ImageBuffer previous_basecolor;
  // previous_frame's denoised latent when the state kept one ("previous_latent":
  // "reuse"); empty: the VAE encodes previous_frame (always for a keyframe).
  // The batcher takes it only when it made it (LatentBuffer::source).
  LatentBuffer previous_latent;
  // True when previous_frame is a keyframe sent with this frame.
  bool reseeded = false;
};

// Ownership: held by std::shared_ptr (the store's and each frame worker's).
// Thread-safety: every method may be called from any thread; a per-session
// mutex serialises them. Lock order: SessionStore's mutex before this one;
// nothing here calls out while holding it except ReadFrameContext's callback.
class Session {
 public:
  // `clock` must outlive the session. The store creates sessions; tests may
  // too. `state.settings()` fixes the environment and size for good.
  Session(std::string id, std::string client_identity, SessionState state, const Clock* clock);

  Session(const Session&) = delete;
  Session& operator=(const Session&) = delete;

  // Immutable after construction; safe without locking.
  const std::string& id() const { return id_; }
  const std::string& client_identity() const { return client_identity_; }
  const SessionSettings& settings() const { return settings_; }
  const std::string& environment() const { return settings_.environment; }

  // Claims the session for frame `frame_index`. FAILED_PRECONDITION if a
  // frame is already in flight, if frame_index is not greater than the last
  // rendered frame's, or if the session has ended for a reason other than
  // draining (a draining server still answers the frames it has read).
  // INVALID_ARGUMENT if `reseed` has the wrong size. Marks activity.
  absl::Status TryBeginFrame(uint64_t frame_index, std::optional<Keyframe> reseed = std::nullopt)
      ABSL_LOCKS_EXCLUDED(mu_);

  // Calls fn with the in-flight frame's context while holding the session's
  // lock in shared mode (fn must not call back into this session).
  // FAILED_PRECONDITION if frame_index is not the frame in flight.
  absl::Status ReadFrameContext(uint64_t frame_index,
                                absl::FunctionRef<void(const FrameContext&)> fn) const
      ABSL_LOCKS_EXCLUDED(mu_);

  // Ends the in-flight frame successfully: output/basecolor (uint8 HWC RGB)
  // become the previous frame/basecolor, `latent` (empty unless the
  // environment reuses latents) the previous latent, and the frame counter
  // advances (see SessionState::CommitFrame). Allowed after the session ended (the frame
  // was already running). FAILED_PRECONDITION if frame_index is not in
  // flight; INVALID_ARGUMENT on a size mismatch, in which case the frame
  // stays in flight (call AbortFrame). Marks activity.
  absl::Status CommitFrame(uint64_t frame_index, ImageBuffer output, ImageBuffer basecolor,
                           LatentBuffer latent = {}) ABSL_LOCKS_EXCLUDED(mu_);

  // Ends the in-flight frame without changing the state (error, cancel).
  // FAILED_PRECONDITION if frame_index is not in flight. Marks activity.
  absl::Status AbortFrame(uint64_t frame_index) ABSL_LOCKS_EXCLUDED(mu_);

  // The frame_index in flight, if any.
  std::optional<uint64_t> frame_in_flight() const ABSL_LOCKS_EXCLUDED(mu_);
  // The last rendered frame's index, if any (SessionOpened.last_frame_index).
  std::optional<uint64_t> last_frame_index() const ABSL_LOCKS_EXCLUDED(mu_);
  // Frames rendered so far.
  uint64_t frame_counter() const ABSL_LOCKS_EXCLUDED(mu_);

  // Marks client activity (e.g. a resume or a keep-alive), postponing idle
  // expiry.
  void Touch() ABSL_LOCKS_EXCLUDED(mu_);
  absl::Time last_activity() const ABSL_LOCKS_EXCLUDED(mu_);
  // True if idle for at least `timeout` at `now` with no frame in flight.
  bool IsIdle(absl::Time now, absl::Duration timeout) const ABSL_LOCKS_EXCLUDED(mu_);

  // Set once by the store when the session ends; never cleared.
  std::optional<EndReason> end_reason() const ABSL_LOCKS_EXCLUDED(mu_);

  // A stream whose client half-closed answered every frame and ended; the
  // session closes once that stream's end is confirmed (the call completed,
  // not broken), and stays open if the call broke instead. While the close
  // is pending, a stream resuming the session waits for the outcome (the
  // server's StreamController sets and clears it).
  void SetClosePending(bool pending) ABSL_LOCKS_EXCLUDED(mu_);
  bool close_pending() const ABSL_LOCKS_EXCLUDED(mu_);

  // A copy of the state (1.5 MiB at 512x512), without the frame in flight.
  SessionState StateSnapshot() const ABSL_LOCKS_EXCLUDED(mu_);
  // ExportState(StateSnapshot()) without the intermediate copy (state_blob.h).
  absl::StatusOr<std::string> ExportState() const ABSL_LOCKS_EXCLUDED(mu_);
  // Memory the session's state holds (SessionState::MemoryBytes), plus a
  // pending re-seed keyframe if one is in flight.
  size_t MemoryBytes() const ABSL_LOCKS_EXCLUDED(mu_);

 private:
  friend class SessionStore;
  // Records the end once (later calls are ignored); returns true the first
  // time. Called by the store.
  bool MarkEnded(EndReason reason) ABSL_LOCKS_EXCLUDED(mu_);
  // MarkEnded(reason) if IsIdle(now, timeout), atomically, so that a frame
  // beginning concurrently either starts first (and the session is not idle)
  // or finds the session ended. Returns whether it ended the session.
  bool MarkEndedIfIdle(absl::Time now, absl::Duration timeout, EndReason reason)
      ABSL_LOCKS_EXCLUDED(mu_);

  absl::Status CheckInFlight(uint64_t frame_index) const ABSL_SHARED_LOCKS_REQUIRED(mu_);

  const std::string id_;
  const std::string client_identity_;
  const SessionSettings settings_;
  const Clock* const clock_;

  mutable absl::Mutex mu_;
  SessionState state_ ABSL_GUARDED_BY(mu_);
  std::optional<uint64_t> in_flight_ ABSL_GUARDED_BY(mu_);
  std::optional<Keyframe> in_flight_reseed_ ABSL_GUARDED_BY(mu_);
  absl::Time last_activity_ ABSL_GUARDED_BY(mu_);
  std::optional<EndReason> end_reason_ ABSL_GUARDED_BY(mu_);
  bool close_pending_ ABSL_GUARDED_BY(mu_) = false;
};

}  // namespace fd::session

#endif  // FD_SESSION_SESSION_H_

// StreamController: the gRPC-free half of one Render stream. It attaches
// the stream to a session (open or resume), decodes and orders frames,
// hands them to the environment's frame queue one at a time, keeps the
// answers in frame order and decides when to read, what to write and when
// the stream ends. RenderStream (render_stream.h) is the callback reactor
// around it: it keeps one write in flight and reports reads and writes.
//
// Lifecycle (StreamPhase), every transition goes through this class:
//
//   kOpening --open--> kOpen --Drain--> kDraining --answered--> kClosed
//       |                 ^  \--half-close, answered; error; cancel--^
//       +--resume--> kResuming (the resume answer waits until no frame of
//                    the session is in flight, so its last_frame_index is
//                    final, and until a pending close is decided)
//                    --released--> kOpen
//
// Ends that keep the session resumable: a cancel or broken call, a message
// above --max_message_bytes or one that does not parse. A half-close (the
// client's WritesDone) closes it, but only once the RPC is done and was not
// cancelled (Detach): gRPC reports a read that failed because the call
// broke (e.g. a message above its own size limit) exactly like a
// half-close until then. Between the OK status and that moment the session
// is close-pending, and a resume waits for the outcome.
//
// Answers: every frame read gets a slot in read order; a frame error fills
// its slot at once, a rendered frame when its answer is encoded (on the
// AnswerEncoder thread, off the batcher's worker). Slots are written from
// the front only, so answers leave in frame_index order, errors included.
//
// Flow control: frames read and not yet answered on the wire (pending,
// rendering, encoding, waiting in a slot, or written but not yet completed)
// never exceed the session's max_frames_in_flight; the stream does not read
// beyond that, so HTTP/2 flow control pushes back on a fast client.
//
// Ownership: shared (std::shared_ptr) by its reactor and by every batcher
// or encoder callback in flight, so a callback may arrive after the RPC
// ended; Detach() then cuts the link to the reactor.
// Thread-safety: every public method is thread-safe (one mutex). Calls into
// StreamOutput are made with that mutex held; StreamServices'
// session_released is called without it, server_draining with it (so it
// must not block: the service reads an atomic).
#ifndef FD_SERVER_STREAM_CONTROLLER_H_
#define FD_SERVER_STREAM_CONTROLLER_H_

#include <cstdint>
#include <deque>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <string_view>

#include "absl/base/thread_annotations.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "framediffuser/v1/render_service.pb.h"
#include "server/answer_encoder.h"
#include "server/frame_input.h"
#include "server/metrics.h"
#include "server/open_settings.h"
#include "session/end_reason.h"
#include "session/environment_registry.h"
#include "session/frame_queue.h"
#include "session/session.h"
#include "session/session_store.h"

namespace fd::server {

enum class StreamPhase : uint8_t {
  kOpening,   // waiting for the first message (open or resume)
  kOpen,      // a session is attached; frames flow
  kResuming,  // resumed; the answer waits for the old stream's frame
  kDraining,  // the server drains: nothing more is read, frames read are answered
  kClosed,    // the end status is decided; nothing more is read or rendered
};
std::string_view StreamPhaseName(StreamPhase phase);

// Where the controller's output goes: the reactor (or a test).
class StreamOutput {
 public:
  virtual ~StreamOutput() = default;
  // Writes `response` after the ones before it. `frame_answer`: a
  // RenderedFrame or FrameError (reported back through OnWritten).
  virtual void Write(v1::RenderResponse response, bool frame_answer) = 0;
  // Ends the RPC with `status` once the writes before it are done. Once.
  virtual void Finish(const absl::Status& status) = 0;
  // Reads the next message (answered through OnRead / OnReadFailed).
  virtual void Read() = 0;
};

// What the controller needs from the server around it.
struct StreamServices {
  session::EnvironmentRegistry* registry = nullptr;  // required
  session::SessionStore* store = nullptr;            // required
  ServerMetrics* metrics = nullptr;                  // optional
  SessionLimits limits;
  // Largest request message (--max_message_bytes), named in the error the
  // reactor reports through OnUnreadableMessage (it checks the wire size
  // before parsing). gRPC's own limit is set above it (server.cc), so a
  // larger message is read and refused by the stream, deterministically:
  // it ends with RESOURCE_EXHAUSTED and the session stays resumable. (A
  // message past
  // gRPC's limit fails the read like a half-close; the call is then
  // cancelled, which Detach sees, so the session stays resumable too.)
  uint64_t max_message_bytes = 0;
  // Encodes rendered frames off the batcher's worker; nullptr: on it (tests).
  AnswerEncoder* encoder = nullptr;
  // Whether the server drains (new sessions are refused).
  std::function<bool()> server_draining;
  // A frame this stream left rendering when it ended has completed: a
  // stream that resumed the session may go on.
  std::function<void(const std::string& session_id)> session_released;
};

class StreamController : public std::enable_shared_from_this<StreamController> {
 public:
  // `output` must stay valid until Detach(). `peer` is for logs.
  StreamController(StreamServices services, StreamOutput* output, std::string peer,
                   std::string routing_key);

  // ---- From the reactor ----
  // Authentication result: starts reading the first message, or ends the
  // stream with the error.
  void Start(absl::StatusOr<std::string> client_identity) ABSL_LOCKS_EXCLUDED(mu_);
  // A message arrived. Returns the id of a session this stream just
  // resumed (the caller tells the other streams to let go of it), else "".
  std::string OnRead(const v1::RenderRequest& request) ABSL_LOCKS_EXCLUDED(mu_);
  // A read failed: a half-close, or (`cancelled`) a broken call, which
  // leaves the session resumable (OnCancel follows). Not yet cancelled may
  // still be a broken call: the session's close waits for Detach.
  void OnReadFailed(bool cancelled) ABSL_LOCKS_EXCLUDED(mu_);
  // A message arrived that cannot be used: `wire_bytes` above
  // max_message_bytes (kTooLarge: RESOURCE_EXHAUSTED) or not a RenderRequest
  // (kUnparsable: INVALID_ARGUMENT). Either ends the stream with that status
  // naming the size, and leaves the session resumable.
  enum class Unreadable : uint8_t { kTooLarge, kUnparsable };
  void OnUnreadableMessage(uint64_t wire_bytes, Unreadable why) ABSL_LOCKS_EXCLUDED(mu_);
  // A write completed (`ok` false: the client is gone).
  void OnWritten(bool frame_answer, bool ok) ABSL_LOCKS_EXCLUDED(mu_);
  // The RPC was cancelled (client cancel, deadline, network loss).
  void OnCancel() ABSL_LOCKS_EXCLUDED(mu_);
  // The RPC is done; no more calls into the output. `call_cancelled`: the
  // call did not complete with the status this stream finished with (the
  // client cancelled, or the call broke). A half-close's session close
  // takes effect here, only if !call_cancelled; either way a stream
  // waiting to resume the session is then released (session_released).
  void Detach(bool call_cancelled) ABSL_LOCKS_EXCLUDED(mu_);

  // ---- From the service (its stream-set lock may be held) ----
  // DRAINING notice now; answers the frames already read; UNAVAILABLE.
  void Drain() ABSL_LOCKS_EXCLUDED(mu_);
  // The server ended the session (evicted, expired): notice, unanswered
  // frames dropped, NOT_FOUND naming the reason.
  void EndSession(session::EndReason reason) ABSL_LOCKS_EXCLUDED(mu_);
  // The session was resumed on another stream: ABORTED.
  void LoseToTakeover() ABSL_LOCKS_EXCLUDED(mu_);
  // The session's frame another stream left rendering completed (or the
  // other streams were told to let go): the held resume answer is sent once
  // no frame is in flight, then parked frames go.
  void OnSessionReleased() ABSL_LOCKS_EXCLUDED(mu_);

  std::string session_id() const ABSL_LOCKS_EXCLUDED(mu_);
  StreamPhase phase() const ABSL_LOCKS_EXCLUDED(mu_);

 private:
  struct PendingFrame {
    uint64_t frame_index = 0;
    DecodedFrame decoded;
    absl::Time read_at;
  };
  // One answer, in read order; `response` is set once it is ready.
  struct AnswerSlot {
    uint64_t frame_index = 0;
    std::optional<v1::RenderResponse> response;
  };

  void HandleFirstMessageLocked(const v1::RenderRequest& request)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void HandleOpenLocked(const v1::OpenSession& open) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void HandleResumeLocked(const v1::ResumeSession& resume) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // Sends the held resume answer if no frame of the session is in flight
  // and no close is pending, or ends the stream if the session was closed
  // meanwhile; returns whether it is (still) held.
  bool HoldingResumeAnswerLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void HandleFrameLocked(const v1::RenderRequest& request) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void SubmitNextLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void OnFrameDone(uint64_t frame_index, absl::Time read_at,
                   absl::StatusOr<session::FrameResult> result) ABSL_LOCKS_EXCLUDED(mu_);
  // The wire answer of a rendered frame (runs without the lock).
  static v1::RenderResponse EncodeAnswer(const session::SessionSettings& settings,
                                         uint64_t frame_index, absl::Time read_at,
                                         const session::FrameResult& result);
  void OnAnswerEncoded(uint64_t frame_index, v1::RenderResponse response) ABSL_LOCKS_EXCLUDED(mu_);

  int OutstandingLocked() const ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  std::optional<uint64_t> LastAcceptedIndexLocked() const ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void ContinueReadingLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // Answer slots.
  void OpenSlotLocked(uint64_t frame_index) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void FillSlotLocked(uint64_t frame_index, v1::RenderResponse response)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void FillFrameErrorLocked(uint64_t frame_index, const absl::Status& status)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void FlushAnswersLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // Frame error for a frame refused before it got a slot (index order is
  // kept: it gets the next slot).
  void RejectFrameLocked(uint64_t frame_index, const absl::Status& status)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void WriteLocked(v1::RenderResponse response, bool frame_answer)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void WriteNoticeLocked(session::EndReason reason, const std::string& message)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // Half-closed or draining with everything answered: end the stream.
  void MaybeFinishLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // Drops frames not yet rendered (and their slots), cancels the one
  // rendering, writes the answers already made.
  void AbandonFramesLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // kClosed and Finish(status) after the writes already made. Idempotent.
  void FinishLocked(const absl::Status& status) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void FailOpenLocked(const absl::Status& status, std::string_view kind)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void UnreadableLocked(uint64_t wire_bytes, Unreadable why) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // Ends a stream whose input broke (not a half-close) with `status`,
  // leaving the session resumable; `reason` goes to the log.
  void BreakStreamLocked(const absl::Status& status, std::string_view reason)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);

  const StreamServices services_;
  const std::string peer_;
  const std::string routing_key_;  // x-session-id metadata
  const absl::Time started_at_;

  mutable absl::Mutex mu_;
  StreamOutput* output_ ABSL_GUARDED_BY(mu_);  // nullptr once detached
  StreamPhase phase_ ABSL_GUARDED_BY(mu_) = StreamPhase::kOpening;
  std::string client_identity_ ABSL_GUARDED_BY(mu_);
  std::shared_ptr<session::Session> session_ ABSL_GUARDED_BY(mu_);
  std::string session_id_ ABSL_GUARDED_BY(mu_);
  uint32_t max_frames_in_flight_ ABSL_GUARDED_BY(mu_) = 1;
  // The SessionOpened answering a resume, while kResuming.
  std::optional<v1::RenderResponse> resume_answer_ ABSL_GUARDED_BY(mu_);

  std::deque<PendingFrame> pending_ ABSL_GUARDED_BY(mu_);
  std::optional<uint64_t> rendering_ ABSL_GUARDED_BY(mu_);  // frame index in the batcher
  // Used only through the narrow FrameQueue interface (enqueue, cancel).
  std::shared_ptr<session::FrameQueue> rendering_on_ ABSL_GUARDED_BY(mu_);
  // Frames wait for the session to be released by another stream's frame.
  bool parked_ ABSL_GUARDED_BY(mu_) = false;
  std::deque<AnswerSlot> answers_ ABSL_GUARDED_BY(mu_);
  int unwritten_answers_ ABSL_GUARDED_BY(mu_) = 0;  // handed to the output, not yet written
  uint64_t frames_answered_ ABSL_GUARDED_BY(mu_) = 0;

  bool reading_ ABSL_GUARDED_BY(mu_) = false;
  bool half_closed_ ABSL_GUARDED_BY(mu_) = false;
  // Finished OK after a half-close: the session closes at Detach unless the
  // call turns out cancelled (session_->close_pending() meanwhile).
  bool close_at_detach_ ABSL_GUARDED_BY(mu_) = false;
};

}  // namespace fd::server

#endif  // FD_SERVER_STREAM_CONTROLLER_H_

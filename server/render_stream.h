// One Render stream (gRPC callback reactor): open or resume, then frames in,
// rendered frames (or FrameErrors) out, in order.
//
// Flow control: a session renders one frame at a time (the scheduler's
// per-session order), and the stream reads ahead at most
// max_frames_in_flight frames: frames read but not rendered, the one
// rendering and answers not yet written all count, so a client that sends
// faster than the model renders, or that stops reading its answers, is
// simply not read from (HTTP/2 flow control pushes back to it). No
// callback ever blocks.
//
// Ends: the client half-closing closes the session once every frame read
// is answered (OK). A cancel or network loss cancels the frame rendering
// (dropped at the next step boundary; the session's state is unchanged)
// and leaves the session resumable. Server-side ends send a SessionNotice
// first (DRAINING -> UNAVAILABLE, EVICTED/EXPIRED -> NOT_FOUND).
//
// Lifetime: created by RenderService::Render; deletes itself once gRPC
// called OnDone AND no scheduler callback is outstanding (a frame callback
// may arrive after the RPC ended).
//
// Thread-safety: reactions run on gRPC threads, frame callbacks on the
// environment's scheduler thread, Drain/EndSession on the caller's; one
// mutex serialises them.
#ifndef FD_SERVER_RENDER_STREAM_H_
#define FD_SERVER_RENDER_STREAM_H_

#include <cstdint>
#include <deque>
#include <memory>
#include <optional>
#include <string>

#include "absl/base/thread_annotations.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "framediffuser/v1/render_service.grpc.pb.h"
#include "server/frame_input.h"
#include "session/end_reason.h"
#include "session/frame_scheduler.h"
#include "session/session.h"

namespace fd::server {

class RenderService;

class RenderStream final : public grpc::ServerBidiReactor<v1::RenderRequest, v1::RenderResponse> {
 public:
  RenderStream(RenderService* service, grpc::CallbackServerContext* context);

  void OnReadDone(bool ok) override;
  void OnWriteDone(bool ok) override;
  void OnCancel() override;
  void OnDone() override;

  // ---- From RenderService (its stream-set lock may be held) ----
  // DRAINING notice now; answers the frames already read; UNAVAILABLE.
  void Drain() ABSL_LOCKS_EXCLUDED(mu_);
  // The server ended this stream's session (evicted, expired): notice, drop
  // unanswered frames, NOT_FOUND naming the reason.
  void EndSession(session::EndReason reason) ABSL_LOCKS_EXCLUDED(mu_);
  // The session was resumed on another stream: ABORTED.
  void LoseToTakeover() ABSL_LOCKS_EXCLUDED(mu_);
  // The session's frame that another (ended) stream left rendering has
  // completed, or (from TakeOver) the other streams were told to let go:
  // a held resume answer is sent once no frame is in flight, then frames
  // this stream parked behind the old one can go.
  void OnSessionReleased() ABSL_LOCKS_EXCLUDED(mu_);
  // The attached session's id ("" before open/resume).
  std::string session_id() const ABSL_LOCKS_EXCLUDED(mu_);

 private:
  struct PendingFrame {
    uint64_t frame_index = 0;
    DecodedFrame decoded;
    absl::Time read_at;
  };

  void HandleFirstMessageLocked(const v1::RenderRequest& request) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void HandleOpenLocked(const v1::OpenSession& open) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void HandleResumeLocked(const v1::ResumeSession& resume) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // Sends resume_answer_ if no frame of the session is in flight; returns
  // whether it is (still) held.
  bool HoldingResumeAnswerLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void HandleFrameLocked(const v1::RenderRequest& request) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // Starts rendering the next pending frame if none is rendering.
  void SubmitNextLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void OnFrameDone(uint64_t frame_index, absl::Time read_at,
                   absl::StatusOr<session::FrameResult> result) ABSL_LOCKS_EXCLUDED(mu_);

  // Frames read and not yet answered on the wire (flow control).
  int OutstandingLocked() const ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // The largest frame index accepted so far (pending, rendering or rendered).
  std::optional<uint64_t> LastAcceptedIndexLocked() const ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void ContinueReadingLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void QueueWriteLocked(v1::RenderResponse response, bool is_frame_answer)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void QueueFrameErrorLocked(uint64_t frame_index, const absl::Status& status)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void QueueNoticeLocked(session::EndReason reason, const std::string& message)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void StartNextWriteLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // Half-closed or draining with nothing left to answer: end the stream.
  void MaybeFinishLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // Drops frames not yet rendered and cancels the one rendering.
  void AbandonFramesLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // Finishes after the writes already queued (a Finish must not overtake
  // an outstanding write). Idempotent.
  void FinishLocked(const absl::Status& status) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // Ends the stream because of an error in the first message.
  void FailOpenLocked(const absl::Status& status, std::string_view kind)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  bool ShouldDeleteLocked() const ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);

  RenderService* const service_;
  grpc::CallbackServerContext* const context_;
  const absl::Time started_at_;

  mutable absl::Mutex mu_;
  std::string client_identity_ ABSL_GUARDED_BY(mu_);
  std::string routing_key_ ABSL_GUARDED_BY(mu_);  // x-session-id metadata
  v1::RenderRequest request_ ABSL_GUARDED_BY(mu_);
  std::shared_ptr<session::Session> session_ ABSL_GUARDED_BY(mu_);
  std::string session_id_ ABSL_GUARDED_BY(mu_);
  uint32_t max_frames_in_flight_ ABSL_GUARDED_BY(mu_) = 1;

  std::deque<PendingFrame> pending_ ABSL_GUARDED_BY(mu_);
  std::optional<uint64_t> rendering_ ABSL_GUARDED_BY(mu_);  // frame index in the scheduler
  std::shared_ptr<session::FrameScheduler> rendering_on_ ABSL_GUARDED_BY(mu_);
  int callbacks_outstanding_ ABSL_GUARDED_BY(mu_) = 0;
  // A resumed session still had the previous stream's frame rendering (it is
  // cancelled at the next step boundary): pending frames wait for it.
  bool waiting_for_session_ ABSL_GUARDED_BY(mu_) = false;
  // The SessionOpened answering a resume, held until no frame of the
  // session is in flight, so its last_frame_index is final: the broken
  // stream's frame may still complete (past its last step boundary) rather
  // than be cancelled, and the client must hear that it did.
  std::optional<v1::RenderResponse> resume_answer_ ABSL_GUARDED_BY(mu_);
  uint64_t frames_answered_ ABSL_GUARDED_BY(mu_) = 0;

  std::deque<v1::RenderResponse> writes_ ABSL_GUARDED_BY(mu_);
  int unsent_frame_answers_ ABSL_GUARDED_BY(mu_) = 0;
  bool writing_ ABSL_GUARDED_BY(mu_) = false;
  std::deque<bool> write_is_frame_answer_ ABSL_GUARDED_BY(mu_);

  bool reading_ ABSL_GUARDED_BY(mu_) = false;
  bool half_closed_ ABSL_GUARDED_BY(mu_) = false;
  bool draining_ ABSL_GUARDED_BY(mu_) = false;
  bool finishing_ ABSL_GUARDED_BY(mu_) = false;
  bool finished_ ABSL_GUARDED_BY(mu_) = false;
  bool done_ ABSL_GUARDED_BY(mu_) = false;
  std::optional<absl::Status> finish_status_ ABSL_GUARDED_BY(mu_);
};

}  // namespace fd::server

#endif  // FD_SERVER_RENDER_STREAM_H_

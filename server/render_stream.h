// One Render stream: the gRPC callback reactor around a StreamController
// (stream_controller.h), which holds the stream's logic (open/resume,
// frames, answer order, flow control, lifecycle). The reactor only moves
// messages: it reads when the controller asks, keeps one write in flight
// from its queue, and reports reads, writes, cancellation and the end.
//
// Messages travel as raw bytes (the service registers Render as a raw
// callback method) and are parsed and serialised here: with typed reads
// gRPC reports a message that does not parse exactly like a half-close,
// which would close the session, while the proto promises that only the
// client's WritesDone does. Raw reads also let a message above
// --max_message_bytes be refused by its size, before parsing it.
//
// Ends: the client half-closing closes the session once every frame read
// is answered (OK) and the call completed. A cancel, network loss or an
// unusable message (too large, not a RenderRequest) cancels the frame
// rendering and leaves the session resumable. Server-side ends send a SessionNotice
// first (DRAINING -> UNAVAILABLE, EVICTED/EXPIRED -> NOT_FOUND).
//
// Lifetime: created by RenderService::Render; deletes itself in OnDone.
// The controller is shared with the callbacks still in flight, which may
// arrive after the RPC ended (it is detached from the reactor first).
//
// Thread-safety: reactions run on gRPC threads, the controller's calls on
// any thread (batcher, encoder, service); the write queue has its own
// mutex, taken after the controller's (never the other way round).
#ifndef FD_SERVER_RENDER_STREAM_H_
#define FD_SERVER_RENDER_STREAM_H_

#include <deque>
#include <memory>
#include <optional>
#include <string>

#include "absl/base/thread_annotations.h"
#include "absl/status/status.h"
#include "absl/synchronization/mutex.h"
#include "framediffuser/v1/render_service.grpc.pb.h"
#include "grpcpp/support/byte_buffer.h"
#include "server/stream_controller.h"
#include "session/end_reason.h"

namespace fd::server {

class RenderService;

class RenderStream final : public grpc::ServerBidiReactor<grpc::ByteBuffer, grpc::ByteBuffer>,
                           private StreamOutput {
 public:
  RenderStream(RenderService* service, grpc::CallbackServerContext* context);

  void OnReadDone(bool ok) override;
  void OnWriteDone(bool ok) override;
  void OnCancel() override;
  void OnDone() override;

  // ---- From RenderService (its stream-set lock may be held) ----
  void Drain() { controller_->Drain(); }
  void EndSession(session::EndReason reason) { controller_->EndSession(reason); }
  void LoseToTakeover() { controller_->LoseToTakeover(); }
  void OnSessionReleased() { controller_->OnSessionReleased(); }
  std::string session_id() const { return controller_->session_id(); }

 private:
  // StreamOutput (called with the controller's lock held).
  void Write(v1::RenderResponse response, bool frame_answer) override ABSL_LOCKS_EXCLUDED(mu_);
  void Finish(const absl::Status& status) override ABSL_LOCKS_EXCLUDED(mu_);
  void Read() override;

  // Starts the next write, or the Finish once every write went out.
  void StartNextWriteLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);

  RenderService* const service_;
  grpc::CallbackServerContext* const context_;
  std::shared_ptr<StreamController> controller_;
  grpc::ByteBuffer read_buffer_;  // one read at a time

  absl::Mutex mu_;
  struct QueuedWrite {
    grpc::ByteBuffer message;  // a serialised v1::RenderResponse
    bool frame_answer = false;
  };
  std::deque<QueuedWrite> writes_ ABSL_GUARDED_BY(mu_);  // front: in flight when writing_
  bool writing_ ABSL_GUARDED_BY(mu_) = false;
  std::optional<absl::Status> finish_status_ ABSL_GUARDED_BY(mu_);
  bool finished_ ABSL_GUARDED_BY(mu_) = false;
};

}  // namespace fd::server

#endif  // FD_SERVER_RENDER_STREAM_H_

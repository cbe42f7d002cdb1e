// Internal: the machinery behind fd::client::Session (see session.h for the
// contract). One synchronous gRPC bidi stream per session:
//  - callers' threads copy frames into requests and write them (Pump), under
//    write_mu_, in submission order, at most window_ outstanding;
//  - one receiver thread reads responses, matches them to the outstanding
//    frames in order, runs callbacks, and on a broken stream runs failover
//    (resume, else a new session from the last received frame) and re-sends
//    every unanswered frame.
// Lock order: write_mu_ before mu_. Callbacks run with no lock held.
#ifndef FD_CLIENT_SDK_INTERNAL_SESSION_IMPL_H_
#define FD_CLIENT_SDK_INTERNAL_SESSION_IMPL_H_

#include <grpcpp/grpcpp.h>

#include <condition_variable>
#include <deque>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/time/time.h"
#include "client_sdk/internal/connection.h"
#include "client_sdk/session.h"
#include "framediffuser/v1/render_service.grpc.pb.h"

namespace fd::client {

class SessionImpl {
 public:
  // Opens the session (blocking); the receiver thread runs afterwards.
  static absl::StatusOr<std::unique_ptr<SessionImpl>> Open(std::shared_ptr<Connection> connection,
                                                           const SessionOptions& options);
  ~SessionImpl();

  std::string session_id() const;
  SessionSettings settings() const;
  uint32_t frames_in_flight() const;
  int failover_count() const;

  absl::Status Submit(const FrameRequest& request, Session::FrameCallback done);
  absl::Status Close();

 private:
  using Request = ::framediffuser::v1::RenderRequest;
  using Response = ::framediffuser::v1::RenderResponse;

  // A gRPC call: its context and stream live and die together.
  struct Call {
    grpc::ClientContext context;
    std::unique_ptr<grpc::ClientReaderWriter<Request, Response>> stream;
  };
  struct Opened {
    std::shared_ptr<Call> call;
    ::framediffuser::v1::SessionOpened opened;
  };
  struct Pending {
    uint64_t frame_index = 0;
    std::shared_ptr<const Request> request;
    Session::FrameCallback done;
  };
  enum class State { kStreaming, kRecovering, kDone };

  SessionImpl(std::shared_ptr<Connection> connection, const SessionOptions& options);

  // Starts a Render call, sends `first` (open or resume) and waits for
  // SessionOpened until `deadline`. `routing_key` goes out as x-session-id.
  absl::StatusOr<Opened> Handshake(const Request& first, const std::string& routing_key,
                                   absl::Time deadline, bool wait_for_ready);
  // Adopts a freshly opened call (under write_mu_ + mu_).
  void InstallLocked(Opened opened);
  // Writes unsent frames in order on the current call.
  void Pump();
  void ReceiverLoop();
  // Handles one response; a non-OK status is a protocol violation.
  absl::Status HandleResponse(Response* response);
  // Failover after the stream broke with `cause`; OK when streaming again.
  absl::Status Recover(const absl::Status& cause);
  Request BuildFailoverOpen() const;
  // Fails every outstanding frame with `status` and ends the session.
  void FailAll(const absl::Status& status);

  const std::shared_ptr<Connection> connection_;
  SessionOptions options_;  // image views cleared: they may dangle
  Request open_request_;    // the original open, keyframe copied in

  std::mutex write_mu_;  // serialises Write/WritesDone on the current call
  mutable std::mutex mu_;
  std::condition_variable cv_;
  State state_ = State::kStreaming;
  absl::Status failure_;  // why the session ended (kDone)
  std::shared_ptr<Call> call_;
  grpc::ClientContext* handshake_context_ = nullptr;  // to cancel from ~SessionImpl
  std::deque<Pending> pending_;                       // unanswered, in order
  size_t sent_ = 0;                                   // pending_[0, sent_) were written on call_
  std::optional<uint64_t> last_received_index_;
  std::shared_ptr<const std::string> last_output_;        // raw pixels of the last frame
  ::framediffuser::v1::Image last_output_shape_;          // its shape (no data)
  std::shared_ptr<const Request> last_answered_request_;  // for its basecolor
  std::optional<::framediffuser::v1::SessionNotice> last_notice_;
  std::string session_id_;
  std::string resume_token_;
  SessionSettings settings_;
  uint32_t window_ = 1;
  int failover_count_ = 0;
  bool close_requested_ = false;
  bool shutting_down_ = false;
  std::thread receiver_;
};

// A fresh 128-bit random id as 32 lowercase hex characters (x-session-id of
// a new session, so a sticky balancer can route its resumes).
std::string NewRoutingKey();

}  // namespace fd::client

#endif  // FD_CLIENT_SDK_INTERNAL_SESSION_IMPL_H_

// The framediffuser.v1.FrameDiffuser service (gRPC callback API):
// ListEnvironments and the Render stream (server/render_stream.h), plus the
// registry of open streams that server-side events reach: draining, a
// session evicted or expired, a session resumed on another stream.
//
// Ownership: borrows the registry, store, metrics and authenticator (all
// must outlive the service and every stream, i.e. the grpc::Server).
// Thread-safety: every public method is thread-safe. Lock order: the
// service's stream-set mutex, then a stream's mutex, then the session store's,
// then a session's; the frame batcher's mutex is never held while calling
// back into a stream.
#ifndef FD_SERVER_RENDER_SERVICE_H_
#define FD_SERVER_RENDER_SERVICE_H_

#include <atomic>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/container/flat_hash_set.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "framediffuser/v1/render_service.grpc.pb.h"
#include "server/answer_encoder.h"
#include "server/auth.h"
#include "server/metrics.h"
#include "server/open_settings.h"
#include "session/end_reason.h"
#include "session/environment_registry.h"
#include "session/session.h"
#include "session/session_store.h"

namespace fd::server {

class RenderStream;

struct RenderServiceDeps {
  session::EnvironmentRegistry* registry = nullptr;  // required
  session::SessionStore* store = nullptr;            // required
  ServerMetrics* metrics = nullptr;                  // optional
  const TokenAuthenticator* auth = nullptr;          // optional: nullptr = no auth
  SessionLimits limits;
  uint64_t max_message_bytes = 0;  // --max_message_bytes; 0: not checked by the streams
};

// Render is registered as a raw callback method (RenderStream parses and
// serialises the messages itself; render_stream.h says why), the other
// methods as typed ones.
class RenderService final
    : public v1::FrameDiffuser::WithCallbackMethod_ListEnvironments<
          v1::FrameDiffuser::WithRawCallbackMethod_Render<v1::FrameDiffuser::Service>> {
 public:
  explicit RenderService(RenderServiceDeps deps);
  ~RenderService() override;

  grpc::ServerUnaryReactor* ListEnvironments(grpc::CallbackServerContext* context,
                                             const v1::ListEnvironmentsRequest* request,
                                             v1::ListEnvironmentsResponse* response) override;
  grpc::ServerBidiReactor<grpc::ByteBuffer, grpc::ByteBuffer>* Render(
      grpc::CallbackServerContext* context) override;

  // Tells every open stream that the server drains: each sends a DRAINING
  // notice, stops reading, answers the frames it already read and ends with
  // UNAVAILABLE. (The caller drains the session store first, so that no new
  // session opens.)
  void BeginDrain() ABSL_LOCKS_EXCLUDED(streams_mu_);
  // Waits until no stream is open, at most until `deadline`; true if none is.
  bool AwaitNoStreams(absl::Time deadline) ABSL_LOCKS_EXCLUDED(streams_mu_);
  // Sessions the server ended (evicted, expired): their streams, if any, get
  // a notice with the reason and end with NOT_FOUND naming it.
  void EndStreamsOf(const std::vector<std::shared_ptr<session::Session>>& sessions,
                    session::EndReason reason) ABSL_LOCKS_EXCLUDED(streams_mu_);
  // A stream that ended had a frame of `session_id` rendering, and it has
  // now completed: the stream that resumed the session may continue. Call
  // without any stream's lock held.
  void SessionReleased(const std::string& session_id) ABSL_LOCKS_EXCLUDED(streams_mu_);
  // Open Render streams.
  int open_streams() const ABSL_LOCKS_EXCLUDED(streams_mu_);

  // ---- For RenderStream ----
  const RenderServiceDeps& deps() const { return deps_; }
  // Encodes rendered frames off the batchers' worker threads.
  AnswerEncoder* encoder() { return &encoder_; }
  // Lock-free: streams ask while holding their own lock.
  bool draining() const { return draining_.load(); }
  // The caller's client identity from the authorization metadata ("" without
  // auth). UNAUTHENTICATED otherwise.
  absl::StatusOr<std::string> Authenticate(const grpc::CallbackServerContext& context) const;
  void AddStream(RenderStream* stream) ABSL_LOCKS_EXCLUDED(streams_mu_);
  void RemoveStream(RenderStream* stream) ABSL_LOCKS_EXCLUDED(streams_mu_);
  // `owner` now holds `session_id`: any other stream attached to it ends
  // (ABORTED "resumed on another stream"). Call without `owner`'s lock held.
  void TakeOver(const std::string& session_id, RenderStream* owner)
      ABSL_LOCKS_EXCLUDED(streams_mu_);

 private:
  const RenderServiceDeps deps_;
  mutable absl::Mutex streams_mu_;
  absl::flat_hash_set<RenderStream*> streams_ ABSL_GUARDED_BY(streams_mu_);
  std::atomic<bool> draining_{false};
  // Declared last: destroyed first, after running what is queued (its
  // tasks only touch stream controllers, which they keep alive).
  AnswerEncoder encoder_;
};

}  // namespace fd::server

#endif  // FD_SERVER_RENDER_SERVICE_H_

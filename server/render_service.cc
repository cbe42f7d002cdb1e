#include "server/render_service.h"

#include <utility>

#include "absl/strings/str_cat.h"
#include "server/log.h"
#include "server/render_stream.h"

namespace fd::server {

RenderService::RenderService(RenderServiceDeps deps) : deps_(std::move(deps)) {}

RenderService::~RenderService() = default;

grpc::ServerUnaryReactor* RenderService::ListEnvironments(
    grpc::CallbackServerContext* context, const v1::ListEnvironmentsRequest* /*request*/,
    v1::ListEnvironmentsResponse* response) {
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  absl::StatusOr<std::string> identity = Authenticate(*context);
  if (!identity.ok()) {
    reactor->Finish(grpc::Status(static_cast<grpc::StatusCode>(identity.status().code()),
                                 std::string(identity.status().message())));
    return reactor;
  }
  for (const session::EnvironmentInfo& info : deps_.registry->List()) {
    *response->add_environments() = ToWireEnvironment(info, deps_.limits);
  }
  reactor->Finish(grpc::Status::OK);
  return reactor;
}

grpc::ServerBidiReactor<grpc::ByteBuffer, grpc::ByteBuffer>* RenderService::Render(
    grpc::CallbackServerContext* context) {
  if (deps_.metrics != nullptr) deps_.metrics->OnStreamStarted();
  return new RenderStream(this, context);
}

absl::StatusOr<std::string> RenderService::Authenticate(
    const grpc::CallbackServerContext& context) const {
  if (deps_.auth == nullptr) return std::string();
  return AuthenticateCall(*deps_.auth, context);
}

void RenderService::AddStream(RenderStream* stream) {
  absl::MutexLock lock(&streams_mu_);
  streams_.insert(stream);
}

void RenderService::RemoveStream(RenderStream* stream) {
  absl::MutexLock lock(&streams_mu_);
  streams_.erase(stream);
}

int RenderService::open_streams() const {
  absl::MutexLock lock(&streams_mu_);
  return static_cast<int>(streams_.size());
}

void RenderService::BeginDrain() {
  draining_.store(true);
  absl::MutexLock lock(&streams_mu_);
  for (RenderStream* stream : streams_) stream->Drain();
}

bool RenderService::AwaitNoStreams(absl::Time deadline) {
  absl::MutexLock lock(&streams_mu_);
  return streams_mu_.AwaitWithDeadline(
      absl::Condition(
          +[](absl::flat_hash_set<RenderStream*>* streams) { return streams->empty(); }, &streams_),
      deadline);
}

void RenderService::EndStreamsOf(const std::vector<std::shared_ptr<session::Session>>& sessions,
                                 session::EndReason reason) {
  if (sessions.empty()) return;
  absl::flat_hash_set<std::string> ids;
  for (const auto& session : sessions) ids.insert(session->id());
  absl::MutexLock lock(&streams_mu_);
  for (RenderStream* stream : streams_) {
    if (ids.contains(stream->session_id())) stream->EndSession(reason);
  }
}

void RenderService::SessionReleased(const std::string& session_id) {
  absl::MutexLock lock(&streams_mu_);
  for (RenderStream* stream : streams_) {
    if (stream->session_id() == session_id) stream->OnSessionReleased();
  }
}

void RenderService::TakeOver(const std::string& session_id, RenderStream* owner) {
  absl::MutexLock lock(&streams_mu_);
  for (RenderStream* stream : streams_) {
    if (stream != owner && stream->session_id() == session_id) stream->LoseToTakeover();
  }
  // If the old stream's frame already completed, nobody else will release
  // the session for frames `owner` may have parked meanwhile; if it is still
  // rendering, the old stream (finishing now) releases it when it completes.
  if (streams_.contains(owner)) owner->OnSessionReleased();
}

}  // namespace fd::server

#include "server/render_stream.h"

#include <utility>

#include "absl/strings/str_cat.h"
#include "base/tsan_annotations.h"
#include "server/render_service.h"

namespace fd::server {
namespace {

grpc::Status ToGrpc(const absl::Status& status) {
  return grpc::Status(static_cast<grpc::StatusCode>(status.code()), std::string(status.message()));
}

std::string RoutingKey(const grpc::CallbackServerContext& context) {
  for (const auto& [key, value] : context.client_metadata()) {
    if (key == "x-session-id") return std::string(value.data(), value.size());
  }
  return "";
}

}  // namespace

RenderStream::RenderStream(RenderService* service, grpc::CallbackServerContext* context)
    : service_(service), context_(context) {
  StreamServices services;
  const RenderServiceDeps& deps = service_->deps();
  services.registry = deps.registry;
  services.store = deps.store;
  services.metrics = deps.metrics;
  services.limits = deps.limits;
  services.max_message_bytes = deps.max_message_bytes;
  services.encoder = service_->encoder();
  services.server_draining = [service] { return service->draining(); };
  services.session_released = [service](const std::string& id) { service->SessionReleased(id); };
  StreamOutput* output = this;
  controller_ = std::make_shared<StreamController>(std::move(services), output, context->peer(),
                                                   RoutingKey(*context));
  service_->AddStream(this);
  controller_->Start(service_->Authenticate(*context));
  // gRPC runs every reaction after this (operations started here wait
  // until the handler returns), ordered inside libgrpc, which TSan cannot
  // see: the reactions acquire this (base/tsan_annotations.h).
  FD_TSAN_RELEASE(this);
}

// ---------------------------------------------------------------- reactions

void RenderStream::OnReadDone(bool ok) {
  FD_TSAN_ACQUIRE(this);
  if (!ok) {
    controller_->OnReadFailed(context_->IsCancelled());
    return;
  }
  const uint64_t wire_bytes = read_buffer_.Length();
  const uint64_t max_bytes = service_->deps().max_message_bytes;
  if (max_bytes > 0 && wire_bytes > max_bytes) {
    read_buffer_.Clear();
    controller_->OnUnreadableMessage(wire_bytes, StreamController::Unreadable::kTooLarge);
    return;
  }
  v1::RenderRequest request;
  // Deserialize consumes (clears) the buffer.
  if (!grpc::SerializationTraits<v1::RenderRequest>::Deserialize(&read_buffer_, &request).ok()) {
    controller_->OnUnreadableMessage(wire_bytes, StreamController::Unreadable::kUnparsable);
    return;
  }
  const std::string takeover = controller_->OnRead(request);
  // Without any stream's lock: the service locks its stream set, then the
  // other streams.
  if (!takeover.empty()) service_->TakeOver(takeover, this);
}

void RenderStream::OnWriteDone(bool ok) {
  FD_TSAN_ACQUIRE(this);
  bool frame_answer = false;
  {
    absl::MutexLock lock(&mu_);
    writing_ = false;
    if (!writes_.empty()) {
      frame_answer = writes_.front().frame_answer;
      writes_.pop_front();
    }
    // The client is gone: nothing more can be delivered.
    if (!ok) writes_.clear();
  }
  // The controller may write, finish or read from here (its lock, then ours).
  controller_->OnWritten(frame_answer, ok);
  absl::MutexLock lock(&mu_);
  StartNextWriteLocked();
}

void RenderStream::OnCancel() {
  FD_TSAN_ACQUIRE(this);
  {
    absl::MutexLock lock(&mu_);
    // Keep the message being written: gRPC still points at it.
    while (writes_.size() > (writing_ ? 1u : 0u)) writes_.pop_back();
  }
  controller_->OnCancel();
}

void RenderStream::OnDone() {
  FD_TSAN_ACQUIRE(this);
  // gRPC runs OnDone after every other reaction has returned, but orders them
  // inside libgrpc++; taking mu_ once (uncontended) makes that order visible
  // to ThreadSanitizer too, which cannot see into Debian's gRPC.
  { absl::MutexLock lock(&mu_); }
  service_->RemoveStream(this);
  // Complete by now (OnDone follows every other reaction), so IsCancelled
  // says for sure whether the call ended with the status we finished with.
  controller_->Detach(context_->IsCancelled());
  delete this;
}

// ------------------------------------------------------------------ output

void RenderStream::Write(v1::RenderResponse response, bool frame_answer) {
  QueuedWrite write;
  write.frame_answer = frame_answer;
  bool own_buffer = false;
  const grpc::Status serialized = grpc::SerializationTraits<v1::RenderResponse>::Serialize(
      response, &write.message, &own_buffer);
  absl::MutexLock lock(&mu_);
  if (finish_status_.has_value()) return;
  if (!serialized.ok()) {
    // Only a message over protobuf's 2 GiB limit fails; ours are bounded.
    finish_status_ = absl::InternalError(
        absl::StrCat("serialising an answer failed: ", serialized.error_message()));
    StartNextWriteLocked();
    return;
  }
  writes_.push_back(std::move(write));
  StartNextWriteLocked();
}

void RenderStream::Finish(const absl::Status& status) {
  absl::MutexLock lock(&mu_);
  if (finish_status_.has_value()) return;
  finish_status_ = status;
  StartNextWriteLocked();
}

void RenderStream::Read() { StartRead(&read_buffer_); }

void RenderStream::StartNextWriteLocked() {
  if (writing_) return;
  if (writes_.empty()) {
    if (finish_status_.has_value() && !finished_) {
      finished_ = true;
      if (service_->deps().metrics) service_->deps().metrics->OnStreamEnded(finish_status_->code());
      ServerBidiReactor::Finish(ToGrpc(*finish_status_));
    }
    return;
  }
  writing_ = true;
  StartWrite(&writes_.front().message);
}

}  // namespace fd::server

#include "server/render_stream.h"

#include <algorithm>
#include <random>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "server/image_codec.h"
#include "server/log.h"
#include "server/open_settings.h"
#include "server/render_service.h"
#include "session/random_token.h"
#include "session/session_state.h"

namespace fd::server {
namespace {

grpc::Status ToGrpc(const absl::Status& status) {
  return grpc::Status(static_cast<grpc::StatusCode>(status.code()),
                      std::string(status.message()));
}

double Ms(absl::Duration d) { return absl::ToDoubleMilliseconds(d); }

// A session seed for OpenSession.seed = 0 (reported back in the settings).
uint64_t RandomSeed() {
  static thread_local std::mt19937_64 engine(std::random_device{}());
  uint64_t seed = 0;
  while (seed == 0) seed = engine();
  return seed;
}

std::string ClientPeer(const grpc::CallbackServerContext& context) { return context.peer(); }

}  // namespace

RenderStream::RenderStream(RenderService* service, grpc::CallbackServerContext* context)
    : service_(service), context_(context), started_at_(absl::Now()) {
  service_->AddStream(this);
  absl::StatusOr<std::string> identity = service_->Authenticate(*context);
  absl::MutexLock lock(&mu_);
  for (const auto& [key, value] : context->client_metadata()) {
    if (key == "x-session-id") routing_key_.assign(value.data(), value.size());
  }
  if (!identity.ok()) {
    LogWarning("auth_denied", {{"peer", ClientPeer(*context)}, {"rpc", "Render"},
                               {"message", std::string(identity.status().message())}});
    FinishLocked(identity.status());
    return;
  }
  client_identity_ = *std::move(identity);
  reading_ = true;
  StartRead(&request_);
}

// ---------------------------------------------------------------- reactions

void RenderStream::OnReadDone(bool ok) {
  std::string takeover;
  {
    absl::MutexLock lock(&mu_);
    reading_ = false;
    if (!ok) {
      // A failed read is a half-close OR a broken call. Only a half-close
      // closes the session; a broken call leaves it resumable (OnCancel).
      if (context_->IsCancelled()) return;
      half_closed_ = true;
      MaybeFinishLocked();
      return;
    }
    if (finishing_) return;
    const bool first = session_ == nullptr;
    if (first) {
      HandleFirstMessageLocked(request_);
      if (request_.has_resume() && session_ != nullptr) takeover = session_id_;
    } else {
      HandleFrameLocked(request_);
    }
    ContinueReadingLocked();
  }
  // Outside our lock: the service locks its stream set, then other streams.
  if (!takeover.empty()) service_->TakeOver(takeover, this);
}

void RenderStream::OnWriteDone(bool ok) {
  absl::MutexLock lock(&mu_);
  writing_ = false;
  if (!writes_.empty()) {
    if (write_is_frame_answer_.front()) --unsent_frame_answers_;
    writes_.pop_front();
    write_is_frame_answer_.pop_front();
  }
  if (!ok) {
    // The client is gone: nothing more can be delivered.
    writes_.clear();
    write_is_frame_answer_.clear();
    unsent_frame_answers_ = 0;
    AbandonFramesLocked();
    FinishLocked(absl::CancelledError("write failed: the client went away"));
  }
  StartNextWriteLocked();
  ContinueReadingLocked();
  MaybeFinishLocked();
}

void RenderStream::OnCancel() {
  absl::MutexLock lock(&mu_);
  // Keep the message being written: gRPC still points at it.
  while (writes_.size() > (writing_ ? 1u : 0u)) {
    writes_.pop_back();
    write_is_frame_answer_.pop_back();
  }
  unsent_frame_answers_ = writing_ && write_is_frame_answer_.front() ? 1 : 0;
  AbandonFramesLocked();
  if (session_ != nullptr) {
    LogEvent("session_detach", {{"session_id", session_id_},
                                {"environment", session_->environment()},
                                {"reason", "cancelled"},
                                {"frames", frames_answered_},
                                {"stream_seconds", absl::ToDoubleSeconds(absl::Now() - started_at_)}});
  }
  FinishLocked(absl::CancelledError("cancelled"));
}

void RenderStream::OnDone() {
  service_->RemoveStream(this);
  bool remove = false;
  {
    absl::MutexLock lock(&mu_);
    done_ = true;
    remove = ShouldDeleteLocked();
  }
  if (remove) delete this;
}

bool RenderStream::ShouldDeleteLocked() const { return done_ && callbacks_outstanding_ == 0; }

// ---------------------------------------------------------- service events

void RenderStream::Drain() {
  absl::MutexLock lock(&mu_);
  if (finishing_ || draining_) return;
  draining_ = true;
  if (session_ != nullptr) {
    QueueNoticeLocked(session::EndReason::kDraining,
                      "the server is shutting down; frames already sent are answered, then the "
                      "stream ends: open a new session elsewhere with the last frame as keyframe");
  }
  MaybeFinishLocked();
}

void RenderStream::EndSession(session::EndReason reason) {
  absl::MutexLock lock(&mu_);
  if (finishing_ || session_ == nullptr) return;
  std::string detail;
  if (std::optional<session::EndedSessionInfo> info =
          service_->deps().store->EndedInfo(session_id_);
      info.has_value()) {
    detail = info->detail;
  }
  const absl::Status ended = session::SessionEndedError(session_id_, reason, detail);
  AbandonFramesLocked();
  QueueNoticeLocked(reason, std::string(ended.message()));
  LogEvent("session_end", {{"session_id", session_id_},
                           {"environment", session_->environment()},
                           {"reason", session::EndReasonName(reason)},
                           {"detail", detail},
                           {"frames", frames_answered_}});
  FinishLocked(ended);
}

void RenderStream::LoseToTakeover() {
  absl::MutexLock lock(&mu_);
  if (finishing_) return;
  AbandonFramesLocked();
  FinishLocked(absl::AbortedError(
      absl::StrCat("session ", session_id_, " was resumed on another stream")));
}

std::string RenderStream::session_id() const {
  absl::MutexLock lock(&mu_);
  return session_id_;
}

// ------------------------------------------------------------ first message

void RenderStream::HandleFirstMessageLocked(const v1::RenderRequest& request) {
  if (request.has_open()) {
    HandleOpenLocked(request.open());
  } else if (request.has_resume()) {
    HandleResumeLocked(request.resume());
  } else if (request.has_frame()) {
    FailOpenLocked(absl::FailedPreconditionError(
                       "frame: the first message must be open or resume, got a frame"),
                   "open");
  } else {
    FailOpenLocked(absl::InvalidArgumentError("request: no open, resume or frame set"), "open");
  }
}

void RenderStream::FailOpenLocked(const absl::Status& status, std::string_view kind) {
  LogWarning("session_open_failed", {{"kind", kind},
                                     {"code", absl::StatusCodeToString(status.code())},
                                     {"message", std::string(status.message())},
                                     {"peer", ClientPeer(*context_)}});
  FinishLocked(status);
}

void RenderStream::HandleOpenLocked(const v1::OpenSession& open) {
  const absl::Time start = absl::Now();
  const RenderServiceDeps& deps = service_->deps();
  if (open.environment().empty()) {
    FailOpenLocked(absl::InvalidArgumentError("open.environment: required"), "open");
    return;
  }
  if (service_->draining()) {
    FailOpenLocked(absl::UnavailableError("the server is draining; open the session elsewhere"),
                   "open");
    return;
  }
  absl::StatusOr<EnvironmentHandle> env = deps.registry->Acquire(open.environment());
  if (!env.ok()) {
    FailOpenLocked(absl::Status(env.status().code(),
                                absl::StrCat("open.environment: ", env.status().message())),
                   "open");
    return;
  }
  absl::StatusOr<session::SessionSettings> settings =
      ResolveOpenSettings(open, env->info, deps.limits, RandomSeed());
  if (!settings.ok()) {
    FailOpenLocked(settings.status(), "open");
    return;
  }
  absl::StatusOr<std::optional<DecodedStartKeyframe>> keyframe =
      DecodeOpenKeyframe(open, settings->width, settings->height);
  if (!keyframe.ok()) {
    FailOpenLocked(keyframe.status(), "open");
    return;
  }
  const bool from_keyframe = keyframe->has_value();
  absl::StatusOr<session::SessionState> state =
      from_keyframe ? session::SessionState::StartFromKeyframe(
                          *settings, std::move((*keyframe)->frame), std::move((*keyframe)->basecolor))
                    : session::SessionState::StartFromGBufferOnly(*settings);
  if (!state.ok()) {
    FailOpenLocked(absl::InvalidArgumentError(absl::StrCat("open: ", state.status().message())),
                   "open");
    return;
  }
  absl::StatusOr<session::CreatedSession> created =
      deps.store->Create(client_identity_, *std::move(state), routing_key_);
  if (!created.ok()) {
    FailOpenLocked(created.status(), "open");
    return;
  }
  session_ = created->session;
  session_id_ = session_->id();
  max_frames_in_flight_ = settings->max_frames_in_flight;

  v1::RenderResponse response;
  v1::SessionOpened* opened = response.mutable_opened();
  opened->set_session_id(session_id_);
  opened->set_resume_token(created->resume_secret);
  *opened->mutable_settings() = ToWireSettings(*settings, from_keyframe);
  opened->set_resumed(false);
  QueueWriteLocked(std::move(response), /*is_frame_answer=*/false);
  LogEvent("session_open", {{"session_id", session_id_},
                            {"environment", settings->environment},
                            {"width", settings->width},
                            {"height", settings->height},
                            {"steps", settings->steps},
                            {"scheduler", session::SchedulerKindName(settings->scheduler)},
                            {"seed", settings->seed},
                            {"from_keyframe", from_keyframe},
                            {"routing_key_adopted", session_id_ == routing_key_},
                            {"open_ms", Ms(absl::Now() - start)},
                            {"peer", ClientPeer(*context_)}});
}

void RenderStream::HandleResumeLocked(const v1::ResumeSession& resume) {
  const RenderServiceDeps& deps = service_->deps();
  if (resume.session_id().empty()) {
    FailOpenLocked(absl::InvalidArgumentError("resume.session_id: required"), "resume");
    return;
  }
  if (!session::IsWellFormedToken(resume.session_id())) {
    FailOpenLocked(absl::InvalidArgumentError(
                       "resume.session_id: expected 32 lowercase hex characters"),
                   "resume");
    return;
  }
  absl::StatusOr<std::shared_ptr<session::Session>> session =
      deps.store->Resume(resume.session_id(), resume.resume_token(), client_identity_);
  if (!session.ok()) {
    if (std::optional<session::EndReason> reason = session::EndReasonFromStatus(session.status());
        reason.has_value()) {
      QueueNoticeLocked(*reason, std::string(session.status().message()));
    }
    FailOpenLocked(absl::Status(session.status().code(),
                                absl::StrCat("resume: ", session.status().message())),
                   "resume");
    return;
  }
  session_ = *std::move(session);
  session_id_ = session_->id();
  const session::SessionSettings& settings = session_->settings();
  max_frames_in_flight_ = std::min(settings.max_frames_in_flight,
                                   std::max<uint32_t>(1, deps.limits.max_frames_in_flight));

  v1::RenderResponse response;
  v1::SessionOpened* opened = response.mutable_opened();
  opened->set_session_id(session_id_);
  *opened->mutable_settings() = ToWireSettings(settings, /*started_from_keyframe=*/false);
  opened->set_resumed(true);
  // Answered from OnSessionReleased, which TakeOver calls once the streams
  // that held the session were told to let go of it (and again when their
  // frame in flight ends); frames sent meanwhile are parked.
  resume_answer_ = std::move(response);
  waiting_for_session_ = true;
}

bool RenderStream::HoldingResumeAnswerLocked() {
  if (!resume_answer_.has_value()) return false;
  if (finishing_) {
    resume_answer_.reset();
    return false;
  }
  if (session_->frame_in_flight().has_value()) return true;
  v1::SessionOpened* opened = resume_answer_->mutable_opened();
  if (std::optional<uint64_t> last = session_->last_frame_index(); last.has_value()) {
    opened->set_last_frame_index(*last);
  }
  LogEvent("session_resume", {{"session_id", session_id_},
                              {"environment", session_->environment()},
                              {"frames_rendered", session_->frame_counter()},
                              {"peer", ClientPeer(*context_)}});
  QueueWriteLocked(*std::move(resume_answer_), /*is_frame_answer=*/false);
  resume_answer_.reset();
  return false;
}

// ------------------------------------------------------------------ frames

std::optional<uint64_t> RenderStream::LastAcceptedIndexLocked() const {
  if (!pending_.empty()) return pending_.back().frame_index;
  if (rendering_.has_value()) return rendering_;
  return session_->last_frame_index();
}

int RenderStream::OutstandingLocked() const {
  return static_cast<int>(pending_.size()) + (rendering_.has_value() ? 1 : 0) +
         unsent_frame_answers_;
}

void RenderStream::HandleFrameLocked(const v1::RenderRequest& request) {
  if (!request.has_frame()) {
    FinishLocked(absl::FailedPreconditionError(
        request.has_open()     ? "open: the session is already open on this stream"
        : request.has_resume() ? "resume: a session is already attached to this stream"
                               : "request: no frame set"));
    return;
  }
  const v1::FrameInput& frame = request.frame();
  const std::string& environment = session_->environment();
  if (std::optional<uint64_t> last = LastAcceptedIndexLocked();
      last.has_value() && frame.frame_index() <= *last) {
    const absl::Status status = absl::FailedPreconditionError(
        absl::StrCat("frame.frame_index: ", frame.frame_index(),
                     " must be greater than the previous frame's ", *last));
    if (service_->deps().metrics) {
      service_->deps().metrics->OnFrameRejectedByServer(environment, status.code());
    }
    QueueFrameErrorLocked(frame.frame_index(), status);
    return;
  }
  absl::StatusOr<DecodedFrame> decoded = DecodeFrameInput(frame, session_->settings());
  if (!decoded.ok()) {
    if (service_->deps().metrics) {
      service_->deps().metrics->OnFrameRejectedByServer(environment, decoded.status().code());
    }
    QueueFrameErrorLocked(frame.frame_index(), decoded.status());
    return;
  }
  pending_.push_back(PendingFrame{frame.frame_index(), *std::move(decoded), absl::Now()});
  SubmitNextLocked();
}

void RenderStream::SubmitNextLocked() {
  while (!rendering_.has_value() && !pending_.empty() && !finishing_ && !waiting_for_session_) {
    PendingFrame frame = std::move(pending_.front());
    pending_.pop_front();
    absl::Status status;
    // Twice at most: a reload may shut the scheduler we were handed down
    // between Acquire and Enqueue (UNAVAILABLE); the next Acquire returns
    // the new one.
    for (int attempt = 0; attempt < 2; ++attempt) {
      absl::StatusOr<EnvironmentHandle> env =
          service_->deps().registry->Acquire(session_->environment());
      if (!env.ok()) {
        status = env.status();
        break;
      }
      session::FrameJob job;
      job.session = session_;
      job.frame_index = frame.frame_index;
      job.reseed = frame.decoded.reseed;
      job.gbuffer = frame.decoded.gbuffer;
      const uint64_t index = frame.frame_index;
      const absl::Time read_at = frame.read_at;
      job.done = [this, index, read_at](absl::StatusOr<session::FrameResult> result) {
        OnFrameDone(index, read_at, std::move(result));
      };
      ++callbacks_outstanding_;
      rendering_ = index;
      rendering_on_ = env->scheduler;
      status = env->scheduler->Enqueue(std::move(job));
      if (status.ok()) return;
      --callbacks_outstanding_;
      rendering_.reset();
      rendering_on_.reset();
      if (status.code() == absl::StatusCode::kFailedPrecondition &&
          session_->frame_in_flight().has_value()) {
        // The frame of the stream this session was resumed from is still
        // rendering (a broken stream's frame stops at the next step
        // boundary). Park until it is released (OnSessionReleased) instead
        // of failing the client's re-sent frames.
        pending_.push_front(std::move(frame));
        waiting_for_session_ = true;
        return;
      }
      if (status.code() != absl::StatusCode::kUnavailable) break;
    }
    // The scheduler's own metrics counted its refusals.
    QueueFrameErrorLocked(frame.frame_index, status);
    if (session_->end_reason().has_value() &&
        *session_->end_reason() != session::EndReason::kDraining) {
      // Ended under us (evicted/expired); EndSession() tells the client.
      AbandonFramesLocked();
      return;
    }
  }
}

void RenderStream::OnSessionReleased() {
  absl::MutexLock lock(&mu_);
  if (HoldingResumeAnswerLocked() || !waiting_for_session_) return;
  waiting_for_session_ = false;
  SubmitNextLocked();
  ContinueReadingLocked();
  MaybeFinishLocked();
}

void RenderStream::OnFrameDone(uint64_t frame_index, absl::Time read_at,
                               absl::StatusOr<session::FrameResult> result) {
  bool remove = false;
  std::string released;  // a session another stream may be waiting for
  {
    absl::MutexLock lock(&mu_);
    if (finishing_) released = session_id_;
    --callbacks_outstanding_;
    if (rendering_ == frame_index) {
      rendering_.reset();
      rendering_on_.reset();
    }
    if (!finishing_) {
      if (result.ok()) {
        v1::RenderResponse response;
        v1::RenderedFrame* rendered = response.mutable_frame();
        rendered->set_frame_index(frame_index);
        const session::SessionSettings& settings = session_->settings();
        absl::Status encoded =
            EncodeImage(settings.width, settings.height, result->image, result->image_float,
                        settings.output_dtype, settings.output_compression,
                        rendered->mutable_image());
        if (!encoded.ok()) {
          QueueFrameErrorLocked(frame_index, encoded);
        } else {
          const session::FrameTimings& t = result->timings;
          v1::StageTimings* timings = rendered->mutable_timings();
          timings->set_queue_ms(t.queue_ms);
          timings->set_encode_ms(t.encode_ms);
          timings->set_denoise_ms(t.denoise_ms);
          timings->set_decode_ms(t.decode_ms);
          timings->set_total_ms(Ms(absl::Now() - read_at));
          timings->set_batch_size(static_cast<uint32_t>(std::max(t.batch_size, 0)));
          ++frames_answered_;
          QueueWriteLocked(std::move(response), /*is_frame_answer=*/true);
        }
      } else if (result.status().code() != absl::StatusCode::kCancelled) {
        LogWarning("frame_failed", {{"session_id", session_id_},
                                    {"frame_index", frame_index},
                                    {"code", absl::StatusCodeToString(result.status().code())},
                                    {"message", std::string(result.status().message())}});
        QueueFrameErrorLocked(frame_index, result.status());
      } else if (!session_->end_reason().has_value()) {
        // Cancelled without the session ending (e.g. by Cancel after a
        // takeover race): the client still gets an answer for the frame.
        QueueFrameErrorLocked(frame_index, result.status());
      }
      SubmitNextLocked();
      ContinueReadingLocked();
      MaybeFinishLocked();
    }
    remove = ShouldDeleteLocked();
  }
  // Outside our lock (the service locks its stream set, then streams).
  RenderService* const service = service_;
  if (remove) delete this;
  if (!released.empty()) service->SessionReleased(released);
}

void RenderStream::AbandonFramesLocked() {
  pending_.clear();
  waiting_for_session_ = false;
  if (rendering_.has_value() && rendering_on_ != nullptr && session_ != nullptr) {
    // Dropped at the next step boundary; its callback still comes (CANCELLED).
    rendering_on_->Cancel(session_id_);
  }
}

// ------------------------------------------------------------------ output

void RenderStream::ContinueReadingLocked() {
  if (finishing_ || reading_ || half_closed_ || draining_ || session_ == nullptr) return;
  if (OutstandingLocked() >= static_cast<int>(max_frames_in_flight_)) return;
  reading_ = true;
  StartRead(&request_);
}

void RenderStream::QueueWriteLocked(v1::RenderResponse response, bool is_frame_answer) {
  if (finishing_) return;
  writes_.push_back(std::move(response));
  write_is_frame_answer_.push_back(is_frame_answer);
  if (is_frame_answer) ++unsent_frame_answers_;
  StartNextWriteLocked();
}

void RenderStream::QueueFrameErrorLocked(uint64_t frame_index, const absl::Status& status) {
  v1::RenderResponse response;
  v1::FrameError* error = response.mutable_frame_error();
  error->set_frame_index(frame_index);
  error->set_code(static_cast<int32_t>(status.code()));
  error->set_message(std::string(status.message()));
  QueueWriteLocked(std::move(response), /*is_frame_answer=*/true);
}

void RenderStream::QueueNoticeLocked(session::EndReason reason, const std::string& message) {
  v1::RenderResponse response;
  v1::SessionNotice* notice = response.mutable_notice();
  notice->set_reason(static_cast<v1::SessionNotice::Reason>(reason));
  notice->set_message(message);
  QueueWriteLocked(std::move(response), /*is_frame_answer=*/false);
}

void RenderStream::StartNextWriteLocked() {
  if (writing_) return;
  if (writes_.empty()) {
    if (finishing_ && !finished_) {
      finished_ = true;
      if (service_->deps().metrics) service_->deps().metrics->OnStreamEnded(finish_status_->code());
      Finish(ToGrpc(*finish_status_));
    }
    return;
  }
  writing_ = true;
  StartWrite(&writes_.front());
}

void RenderStream::MaybeFinishLocked() {
  if (finishing_ || !pending_.empty() || rendering_.has_value()) return;
  // (pending_ is non-empty while waiting_for_session_, unless only the
  // resume answer is held.)
  if (draining_) {
    FinishLocked(absl::UnavailableError(
        "the server is shutting down; open a new session elsewhere"));
    return;
  }
  if (!half_closed_ || resume_answer_.has_value()) return;
  if (session_ != nullptr && !session_->end_reason().has_value()) {
    absl::Status closed = service_->deps().store->Close(session_id_);
    LogEvent("session_close", {{"session_id", session_id_},
                               {"environment", session_->environment()},
                               {"frames", frames_answered_},
                               {"frames_rendered", session_->frame_counter()},
                               {"stream_seconds", absl::ToDoubleSeconds(absl::Now() - started_at_)},
                               {"ok", closed.ok()}});
  }
  FinishLocked(absl::OkStatus());
}

void RenderStream::FinishLocked(const absl::Status& status) {
  if (finishing_) return;
  finishing_ = true;
  finish_status_ = status;
  StartNextWriteLocked();
}

}  // namespace fd::server

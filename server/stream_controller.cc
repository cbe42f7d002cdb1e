#include "server/stream_controller.h"

#include <algorithm>
#include <random>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "server/image_codec.h"
#include "server/log.h"
#include "server/wire_enums.h"
#include "session/random_token.h"
#include "session/session_state.h"

namespace fd::server {
namespace {

double Ms(absl::Duration d) { return absl::ToDoubleMilliseconds(d); }

// A session seed for OpenSession.seed = 0 (reported back in the settings).
uint64_t RandomSeed() {
  static thread_local std::mt19937_64 engine(std::random_device{}());
  uint64_t seed = 0;
  while (seed == 0) seed = engine();
  return seed;
}

v1::RenderResponse FrameErrorResponse(uint64_t frame_index, const absl::Status& status) {
  v1::RenderResponse response;
  v1::FrameError* error = response.mutable_frame_error();
  error->set_frame_index(frame_index);
  error->set_code(static_cast<int32_t>(status.code()));
  error->set_message(std::string(status.message()));
  return response;
}

}  // namespace

std::string_view StreamPhaseName(StreamPhase phase) {
  switch (phase) {
    case StreamPhase::kOpening:
      return "opening";
    case StreamPhase::kOpen:
      return "open";
    case StreamPhase::kResuming:
      return "resuming";
    case StreamPhase::kDraining:
      return "draining";
    case StreamPhase::kClosed:
      return "closed";
  }
  return "unknown";
}

StreamController::StreamController(StreamServices services, StreamOutput* output, std::string peer,
                                   std::string routing_key)
    : services_(std::move(services)),
      peer_(std::move(peer)),
      routing_key_(std::move(routing_key)),
      started_at_(absl::Now()),
      output_(output) {}

// ---------------------------------------------------------------- reactions

void StreamController::Start(absl::StatusOr<std::string> client_identity) {
  absl::MutexLock lock(&mu_);
  if (!client_identity.ok()) {
    LogWarning("auth_denied", {{"peer", peer_},
                               {"rpc", "Render"},
                               {"message", std::string(client_identity.status().message())}});
    FinishLocked(client_identity.status());
    return;
  }
  client_identity_ = *std::move(client_identity);
  reading_ = true;
  if (output_ != nullptr) output_->Read();
}

std::string StreamController::OnRead(const v1::RenderRequest& request) {
  absl::MutexLock lock(&mu_);
  reading_ = false;
  if (phase_ == StreamPhase::kClosed) return "";
  std::string takeover;
  if (phase_ == StreamPhase::kOpening) {
    HandleFirstMessageLocked(request);
    if (phase_ == StreamPhase::kResuming) takeover = session_id_;
  } else {
    HandleFrameLocked(request);
  }
  ContinueReadingLocked();
  return takeover;
}

void StreamController::OnReadFailed(bool cancelled) {
  absl::MutexLock lock(&mu_);
  reading_ = false;
  // A failed read is a half-close OR a broken call. Only a half-close
  // closes the session; a broken call leaves it resumable (OnCancel).
  if (cancelled) return;
  half_closed_ = true;
  MaybeFinishLocked();
}

void StreamController::OnUnreadableMessage(uint64_t wire_bytes, Unreadable why) {
  absl::MutexLock lock(&mu_);
  reading_ = false;
  if (phase_ == StreamPhase::kClosed) return;
  UnreadableLocked(wire_bytes, why);
}

void StreamController::UnreadableLocked(uint64_t wire_bytes, Unreadable why) {
  // A broken stream, not a half-close: the session stays resumable.
  const char* resumable = session_ != nullptr ? "; the session stays resumable" : "";
  switch (why) {
    case Unreadable::kTooLarge:
      BreakStreamLocked(absl::ResourceExhaustedError(absl::StrCat(
                            "request: ", wire_bytes, " bytes, more than --max_message_bytes ",
                            services_.max_message_bytes, resumable)),
                        "message_too_large");
      return;
    case Unreadable::kUnparsable:
      BreakStreamLocked(
          absl::InvalidArgumentError(absl::StrCat(
              "request: ", wire_bytes,
              " bytes that do not parse as a framediffuser.v1.RenderRequest", resumable)),
          "unparsable_message");
      return;
  }
}

void StreamController::BreakStreamLocked(const absl::Status& status, std::string_view reason) {
  AbandonFramesLocked();
  if (session_ != nullptr) {
    LogEvent("session_detach", {{"session_id", session_id_},
                                {"environment", session_->environment()},
                                {"reason", reason},
                                {"frames", frames_answered_}});
  }
  FinishLocked(status);
}

void StreamController::OnWritten(bool frame_answer, bool ok) {
  absl::MutexLock lock(&mu_);
  if (frame_answer && unwritten_answers_ > 0) --unwritten_answers_;
  if (!ok) {
    // The client is gone: nothing more can be delivered.
    unwritten_answers_ = 0;
    AbandonFramesLocked();
    FinishLocked(absl::CancelledError("write failed: the client went away"));
  }
  ContinueReadingLocked();
  MaybeFinishLocked();
}

void StreamController::OnCancel() {
  absl::MutexLock lock(&mu_);
  unwritten_answers_ = 0;
  AbandonFramesLocked();
  if (session_ != nullptr) {
    LogEvent("session_detach",
             {{"session_id", session_id_},
              {"environment", session_->environment()},
              {"reason", "cancelled"},
              {"frames", frames_answered_},
              {"stream_seconds", absl::ToDoubleSeconds(absl::Now() - started_at_)}});
  }
  FinishLocked(absl::CancelledError("cancelled"));
}

void StreamController::Detach(bool call_cancelled) {
  std::string released;
  {
    absl::MutexLock lock(&mu_);
    output_ = nullptr;
    if (close_at_detach_) {
      close_at_detach_ = false;
      released = session_id_;
      if (!call_cancelled) {
        // Closed before the pending flag clears: a resume waiting on it
        // finds the session ended (and one arriving now, NOT_FOUND).
        const absl::Status closed = services_.store->Close(session_id_);
        LogEvent("session_close",
                 {{"session_id", session_id_},
                  {"environment", session_->environment()},
                  {"frames", frames_answered_},
                  {"frames_rendered", session_->frame_counter()},
                  {"stream_seconds", absl::ToDoubleSeconds(absl::Now() - started_at_)},
                  {"ok", closed.ok()}});
      } else {
        // The "half-close" was a read failing on a broken call.
        LogEvent("session_detach", {{"session_id", session_id_},
                                    {"environment", session_->environment()},
                                    {"reason", "call_broken_after_last_read"},
                                    {"frames", frames_answered_}});
      }
      session_->SetClosePending(false);
    }
  }
  if (!released.empty() && services_.session_released) services_.session_released(released);
}

// ---------------------------------------------------------- service events

void StreamController::Drain() {
  absl::MutexLock lock(&mu_);
  if (phase_ == StreamPhase::kClosed || phase_ == StreamPhase::kDraining) return;
  phase_ = StreamPhase::kDraining;
  if (session_ != nullptr) {
    WriteNoticeLocked(session::EndReason::kDraining,
                      "the server is shutting down; frames already sent are answered, then the "
                      "stream ends: open a new session elsewhere with the last frame as keyframe");
  }
  MaybeFinishLocked();
}

void StreamController::EndSession(session::EndReason reason) {
  absl::MutexLock lock(&mu_);
  if (phase_ == StreamPhase::kClosed || session_ == nullptr) return;
  std::string detail;
  if (std::optional<session::EndedSessionInfo> info = services_.store->EndedInfo(session_id_);
      info.has_value()) {
    detail = info->detail;
  }
  const absl::Status ended = session::SessionEndedError(session_id_, reason, detail);
  AbandonFramesLocked();
  WriteNoticeLocked(reason, std::string(ended.message()));
  LogEvent("session_end", {{"session_id", session_id_},
                           {"environment", session_->environment()},
                           {"reason", session::EndReasonName(reason)},
                           {"detail", detail},
                           {"frames", frames_answered_}});
  FinishLocked(ended);
}

void StreamController::LoseToTakeover() {
  absl::MutexLock lock(&mu_);
  if (phase_ == StreamPhase::kClosed) return;
  AbandonFramesLocked();
  FinishLocked(
      absl::AbortedError(absl::StrCat("session ", session_id_, " was resumed on another stream")));
}

void StreamController::OnSessionReleased() {
  absl::MutexLock lock(&mu_);
  if (HoldingResumeAnswerLocked() || !parked_) return;
  parked_ = false;
  SubmitNextLocked();
  ContinueReadingLocked();
  MaybeFinishLocked();
}

std::string StreamController::session_id() const {
  absl::MutexLock lock(&mu_);
  return session_id_;
}

StreamPhase StreamController::phase() const {
  absl::MutexLock lock(&mu_);
  return phase_;
}

// ------------------------------------------------------------ first message

void StreamController::HandleFirstMessageLocked(const v1::RenderRequest& request) {
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

void StreamController::FailOpenLocked(const absl::Status& status, std::string_view kind) {
  LogWarning("session_open_failed", {{"kind", kind},
                                     {"code", absl::StatusCodeToString(status.code())},
                                     {"message", std::string(status.message())},
                                     {"peer", peer_}});
  FinishLocked(status);
}

void StreamController::HandleOpenLocked(const v1::OpenSession& open) {
  const absl::Time start = absl::Now();
  if (open.environment().empty()) {
    FailOpenLocked(absl::InvalidArgumentError("open.environment: required"), "open");
    return;
  }
  if (services_.server_draining && services_.server_draining()) {
    FailOpenLocked(absl::UnavailableError("the server is draining; open the session elsewhere"),
                   "open");
    return;
  }
  absl::StatusOr<session::EnvironmentHandle> env = services_.registry->Acquire(open.environment());
  if (!env.ok()) {
    FailOpenLocked(absl::Status(env.status().code(),
                                absl::StrCat("open.environment: ", env.status().message())),
                   "open");
    return;
  }
  absl::StatusOr<session::SessionSettings> settings =
      ResolveOpenSettings(open, env->info, services_.limits, RandomSeed());
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
      from_keyframe
          ? session::SessionState::StartFromKeyframe(*settings, std::move((*keyframe)->frame),
                                                     std::move((*keyframe)->basecolor))
          : session::SessionState::StartFromGBufferOnly(*settings);
  if (!state.ok()) {
    FailOpenLocked(absl::InvalidArgumentError(absl::StrCat("open: ", state.status().message())),
                   "open");
    return;
  }
  absl::StatusOr<session::CreatedSession> created =
      services_.store->Create(client_identity_, *std::move(state), routing_key_);
  if (!created.ok()) {
    FailOpenLocked(created.status(), "open");
    return;
  }
  session_ = created->session;
  session_id_ = session_->id();
  max_frames_in_flight_ = settings->max_frames_in_flight;
  phase_ = StreamPhase::kOpen;

  v1::RenderResponse response;
  v1::SessionOpened* opened = response.mutable_opened();
  opened->set_session_id(session_id_);
  opened->set_resume_token(created->resume_secret);
  *opened->mutable_settings() = ToWireSettings(*settings, from_keyframe);
  opened->set_resumed(false);
  WriteLocked(std::move(response), /*frame_answer=*/false);
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
                            {"peer", peer_}});
}

void StreamController::HandleResumeLocked(const v1::ResumeSession& resume) {
  if (resume.session_id().empty()) {
    FailOpenLocked(absl::InvalidArgumentError("resume.session_id: required"), "resume");
    return;
  }
  if (!session::IsWellFormedToken(resume.session_id())) {
    FailOpenLocked(
        absl::InvalidArgumentError("resume.session_id: expected 32 lowercase hex characters"),
        "resume");
    return;
  }
  absl::StatusOr<std::shared_ptr<session::Session>> session =
      services_.store->Resume(resume.session_id(), resume.resume_token(), client_identity_);
  if (!session.ok()) {
    if (std::optional<session::EndReason> reason = session::EndReasonFromStatus(session.status());
        reason.has_value()) {
      WriteNoticeLocked(*reason, std::string(session.status().message()));
    }
    FailOpenLocked(
        absl::Status(session.status().code(), absl::StrCat("resume: ", session.status().message())),
        "resume");
    return;
  }
  session_ = *std::move(session);
  session_id_ = session_->id();
  const session::SessionSettings& settings = session_->settings();
  max_frames_in_flight_ = std::min(settings.max_frames_in_flight,
                                   std::max<uint32_t>(1, services_.limits.max_frames_in_flight));

  v1::RenderResponse response;
  v1::SessionOpened* opened = response.mutable_opened();
  opened->set_session_id(session_id_);
  *opened->mutable_settings() = ToWireSettings(settings, /*started_from_keyframe=*/false);
  opened->set_resumed(true);
  // Answered from OnSessionReleased, which the service calls once the
  // streams that held the session were told to let go of it (and again
  // when their frame in flight ends); frames sent meanwhile are parked.
  resume_answer_ = std::move(response);
  phase_ = StreamPhase::kResuming;
  parked_ = true;
}

bool StreamController::HoldingResumeAnswerLocked() {
  if (!resume_answer_.has_value()) return false;
  if (phase_ == StreamPhase::kClosed) {
    resume_answer_.reset();
    return false;
  }
  if (session_->frame_in_flight().has_value() || session_->close_pending()) return true;
  if (std::optional<session::EndReason> reason = session_->end_reason(); reason.has_value()) {
    // The stream it was resumed from closed it (its client's half-close
    // completed) while this answer waited.
    resume_answer_.reset();
    AbandonFramesLocked();
    const absl::Status ended = session::SessionEndedError(session_id_, *reason, "");
    WriteNoticeLocked(*reason, std::string(ended.message()));
    FailOpenLocked(absl::Status(ended.code(), absl::StrCat("resume: ", ended.message())), "resume");
    return false;
  }
  v1::SessionOpened* opened = resume_answer_->mutable_opened();
  if (std::optional<uint64_t> last = session_->last_frame_index(); last.has_value()) {
    opened->set_last_frame_index(*last);
  }
  LogEvent("session_resume", {{"session_id", session_id_},
                              {"environment", session_->environment()},
                              {"frames_rendered", session_->frame_counter()},
                              {"peer", peer_}});
  WriteLocked(*std::move(resume_answer_), /*frame_answer=*/false);
  resume_answer_.reset();
  if (phase_ == StreamPhase::kResuming) phase_ = StreamPhase::kOpen;
  return false;
}

// ------------------------------------------------------------------ frames

std::optional<uint64_t> StreamController::LastAcceptedIndexLocked() const {
  if (!pending_.empty()) return pending_.back().frame_index;
  if (rendering_.has_value()) return rendering_;
  return session_->last_frame_index();
}

int StreamController::OutstandingLocked() const {
  return static_cast<int>(answers_.size()) + unwritten_answers_;
}

void StreamController::HandleFrameLocked(const v1::RenderRequest& request) {
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
    if (services_.metrics != nullptr) {
      services_.metrics->OnFrameRejectedByServer(environment, status.code());
    }
    RejectFrameLocked(frame.frame_index(), status);
    return;
  }
  absl::StatusOr<DecodedFrame> decoded = DecodeFrameInput(frame, session_->settings());
  if (!decoded.ok()) {
    if (services_.metrics != nullptr) {
      services_.metrics->OnFrameRejectedByServer(environment, decoded.status().code());
    }
    RejectFrameLocked(frame.frame_index(), decoded.status());
    return;
  }
  OpenSlotLocked(frame.frame_index());
  pending_.push_back(PendingFrame{frame.frame_index(), *std::move(decoded), absl::Now()});
  SubmitNextLocked();
}

void StreamController::SubmitNextLocked() {
  while (!rendering_.has_value() && !pending_.empty() && phase_ != StreamPhase::kClosed &&
         !parked_) {
    PendingFrame frame = std::move(pending_.front());
    pending_.pop_front();
    absl::Status status;
    // Twice at most: a reload may shut the batcher we were handed down
    // between Acquire and Enqueue (UNAVAILABLE); the next Acquire returns
    // the new one.
    for (int attempt = 0; attempt < 2; ++attempt) {
      absl::StatusOr<session::EnvironmentHandle> env =
          services_.registry->Acquire(session_->environment());
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
      // The callback keeps this controller alive (the RPC may end first).
      job.done = [self = shared_from_this(), index,
                  read_at](absl::StatusOr<session::FrameResult> result) {
        self->OnFrameDone(index, read_at, std::move(result));
      };
      rendering_ = index;
      std::shared_ptr<session::FrameQueue> queue = env->batcher;
      rendering_on_ = queue;
      status = queue->Enqueue(std::move(job));
      if (status.ok()) return;
      rendering_.reset();
      rendering_on_.reset();
      if (status.code() == absl::StatusCode::kFailedPrecondition &&
          session_->frame_in_flight().has_value()) {
        // The frame of the stream this session was resumed from is still
        // rendering (a broken stream's frame stops at the next step
        // boundary). Park until it is released (OnSessionReleased) instead
        // of failing the client's re-sent frames.
        pending_.push_front(std::move(frame));
        parked_ = true;
        return;
      }
      if (status.code() != absl::StatusCode::kUnavailable) break;
    }
    // The batcher's own metrics counted its refusals.
    FillFrameErrorLocked(frame.frame_index, status);
    if (session_->end_reason().has_value() &&
        *session_->end_reason() != session::EndReason::kDraining) {
      // Ended under us (evicted/expired); EndSession() tells the client.
      AbandonFramesLocked();
      return;
    }
  }
}

v1::RenderResponse StreamController::EncodeAnswer(const session::SessionSettings& settings,
                                                  uint64_t frame_index, absl::Time read_at,
                                                  const session::FrameResult& result) {
  v1::RenderResponse response;
  v1::RenderedFrame* rendered = response.mutable_frame();
  rendered->set_frame_index(frame_index);
  const ImageBuffer& image =
      settings.output_dtype == session::OutputDType::kUint8 ? result.image : result.image_float;
  absl::Status encoded = EncodeImage(image, settings.output_dtype, settings.output_compression,
                                     rendered->mutable_image());
  if (!encoded.ok()) return FrameErrorResponse(frame_index, encoded);
  const session::FrameTimings& t = result.timings;
  v1::StageTimings* timings = rendered->mutable_timings();
  timings->set_queue_ms(t.queue_ms);
  timings->set_encode_ms(t.encode_ms);
  timings->set_denoise_ms(t.denoise_ms);
  timings->set_decode_ms(t.decode_ms);
  timings->set_total_ms(Ms(absl::Now() - read_at));
  timings->set_batch_size(static_cast<uint32_t>(std::max(t.batch_size, 0)));
  return response;
}

void StreamController::OnFrameDone(uint64_t frame_index, absl::Time read_at,
                                   absl::StatusOr<session::FrameResult> result) {
  std::string released;  // a session another stream may be waiting for
  std::optional<session::SessionSettings> encode_with;
  {
    absl::MutexLock lock(&mu_);
    if (rendering_ == frame_index) {
      rendering_.reset();
      rendering_on_.reset();
    }
    if (phase_ == StreamPhase::kClosed) {
      released = session_id_;
    } else {
      if (result.ok()) {
        encode_with = session_->settings();  // the slot is filled once encoded
      } else if (result.status().code() != absl::StatusCode::kCancelled) {
        LogWarning("frame_failed", {{"session_id", session_id_},
                                    {"frame_index", frame_index},
                                    {"code", absl::StatusCodeToString(result.status().code())},
                                    {"message", std::string(result.status().message())}});
        FillFrameErrorLocked(frame_index, result.status());
      } else if (!session_->end_reason().has_value()) {
        // Cancelled without the session ending (e.g. by Cancel after a
        // takeover race): the client still gets an answer for the frame.
        FillFrameErrorLocked(frame_index, result.status());
      } else {
        // Cancelled because the session ended: EndSession answers for it.
        answers_.erase(std::remove_if(answers_.begin(), answers_.end(),
                                      [&](const AnswerSlot& slot) {
                                        return slot.frame_index == frame_index &&
                                               !slot.response.has_value();
                                      }),
                       answers_.end());
        FlushAnswersLocked();
      }
      // The session's next frame renders while this one is encoded.
      SubmitNextLocked();
      ContinueReadingLocked();
      MaybeFinishLocked();
    }
  }
  if (encode_with.has_value()) {
    // Encoding (fp16, zstd, the copy into the proto) runs off the batcher's
    // worker thread, which the next batch waits for.
    auto encode = [self = shared_from_this(), settings = *std::move(encode_with), frame_index,
                   read_at, result = *std::move(result)]() {
      self->OnAnswerEncoded(frame_index, EncodeAnswer(settings, frame_index, read_at, result));
    };
    if (services_.encoder != nullptr) {
      services_.encoder->Post(std::move(encode));
    } else {
      encode();
    }
  }
  if (!released.empty() && services_.session_released) services_.session_released(released);
}

void StreamController::OnAnswerEncoded(uint64_t frame_index, v1::RenderResponse response) {
  absl::MutexLock lock(&mu_);
  if (phase_ == StreamPhase::kClosed) return;
  if (response.has_frame()) ++frames_answered_;
  FillSlotLocked(frame_index, std::move(response));
  ContinueReadingLocked();
  MaybeFinishLocked();
}

void StreamController::AbandonFramesLocked() {
  pending_.clear();
  parked_ = false;
  // Answers already made still go out (in order); the ones that will not
  // be made are dropped with their slots.
  answers_.erase(std::remove_if(answers_.begin(), answers_.end(),
                                [](const AnswerSlot& slot) { return !slot.response.has_value(); }),
                 answers_.end());
  FlushAnswersLocked();
  if (rendering_.has_value() && rendering_on_ != nullptr && session_ != nullptr) {
    // Dropped at the next step boundary; its callback still comes (CANCELLED).
    rendering_on_->Cancel(session_id_);
  }
}

// ------------------------------------------------------------------ output

void StreamController::ContinueReadingLocked() {
  if (reading_ || half_closed_ || phase_ == StreamPhase::kClosed ||
      phase_ == StreamPhase::kDraining || session_ == nullptr || output_ == nullptr) {
    return;
  }
  if (OutstandingLocked() >= static_cast<int>(max_frames_in_flight_)) return;
  reading_ = true;
  output_->Read();
}

void StreamController::OpenSlotLocked(uint64_t frame_index) {
  answers_.push_back(AnswerSlot{frame_index, std::nullopt});
}

void StreamController::FillSlotLocked(uint64_t frame_index, v1::RenderResponse response) {
  for (AnswerSlot& slot : answers_) {
    if (slot.frame_index == frame_index && !slot.response.has_value()) {
      slot.response = std::move(response);
      FlushAnswersLocked();
      return;
    }
  }
}

void StreamController::FillFrameErrorLocked(uint64_t frame_index, const absl::Status& status) {
  FillSlotLocked(frame_index, FrameErrorResponse(frame_index, status));
}

void StreamController::RejectFrameLocked(uint64_t frame_index, const absl::Status& status) {
  OpenSlotLocked(frame_index);
  FillFrameErrorLocked(frame_index, status);
}

void StreamController::FlushAnswersLocked() {
  while (!answers_.empty() && answers_.front().response.has_value()) {
    v1::RenderResponse response = *std::move(answers_.front().response);
    answers_.pop_front();
    WriteLocked(std::move(response), /*frame_answer=*/true);
  }
}

void StreamController::WriteLocked(v1::RenderResponse response, bool frame_answer) {
  if (phase_ == StreamPhase::kClosed || output_ == nullptr) return;
  if (frame_answer) ++unwritten_answers_;
  output_->Write(std::move(response), frame_answer);
}

void StreamController::WriteNoticeLocked(session::EndReason reason, const std::string& message) {
  v1::RenderResponse response;
  v1::SessionNotice* notice = response.mutable_notice();
  notice->set_reason(ToWire(reason));
  notice->set_message(message);
  WriteLocked(std::move(response), /*frame_answer=*/false);
}

void StreamController::MaybeFinishLocked() {
  if (phase_ == StreamPhase::kClosed || !pending_.empty() || rendering_.has_value() ||
      !answers_.empty()) {
    return;
  }
  if (phase_ == StreamPhase::kDraining) {
    FinishLocked(
        absl::UnavailableError("the server is shutting down; open a new session elsewhere"));
    return;
  }
  if (!half_closed_ || resume_answer_.has_value()) return;
  if (session_ != nullptr && !session_->end_reason().has_value()) {
    // Closed at Detach, once the call is known not to have broken.
    session_->SetClosePending(true);
    close_at_detach_ = true;
  }
  FinishLocked(absl::OkStatus());
}

void StreamController::FinishLocked(const absl::Status& status) {
  if (phase_ == StreamPhase::kClosed) return;
  phase_ = StreamPhase::kClosed;
  if (output_ != nullptr) output_->Finish(status);
}

}  // namespace fd::server

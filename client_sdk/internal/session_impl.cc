#include "client_sdk/internal/session_impl.h"

#include <algorithm>
#include <chrono>
#include <random>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "client_sdk/internal/wire.h"

namespace fd::client {
namespace {

namespace v1 = ::framediffuser::v1;
using internal::FillImage;
using internal::FromGrpc;

// Cancels a call still in its handshake when the deadline passes. A thread
// per handshake: handshakes are rare (open, failover).
class CallWatchdog {
 public:
  CallWatchdog(grpc::ClientContext* context, absl::Time deadline)
      : thread_([this, context, deadline] {
          std::unique_lock<std::mutex> lock(mu_);
          const auto until =
              std::chrono::steady_clock::now() +
              absl::ToChronoNanoseconds(std::max(deadline - absl::Now(), absl::ZeroDuration()));
          if (!cv_.wait_until(lock, until, [this] { return disarmed_; })) {
            fired_ = true;
            context->TryCancel();
          }
        }) {}
  ~CallWatchdog() { Disarm(); }

  void Disarm() {
    {
      std::lock_guard<std::mutex> lock(mu_);
      disarmed_ = true;
    }
    cv_.notify_all();
    if (thread_.joinable()) thread_.join();
  }
  bool fired() {
    std::lock_guard<std::mutex> lock(mu_);
    return fired_;
  }

 private:
  std::mutex mu_;
  std::condition_variable cv_;
  bool disarmed_ = false;
  bool fired_ = false;
  std::thread thread_;  // last: starts after the members it uses
};

// Resume attempts that fail with UNAVAILABLE before failover opens a new
// session instead (see Recover).
constexpr int kResumeAttempts = 3;

bool IsNotice(const std::optional<v1::SessionNotice>& notice, v1::SessionNotice::Reason reason) {
  return notice.has_value() && notice->reason() == reason;
}

// A broken stream that failover may fix (as opposed to a request the server
// rejected, which would fail again).
bool IsFailoverCause(const absl::Status& cause, const std::optional<v1::SessionNotice>& notice) {
  if (IsNotice(notice, v1::SessionNotice::REASON_DRAINING) ||
      IsNotice(notice, v1::SessionNotice::REASON_EVICTED)) {
    return true;
  }
  switch (cause.code()) {
    case absl::StatusCode::kUnavailable:
    case absl::StatusCode::kCancelled:
    case absl::StatusCode::kAborted:
    case absl::StatusCode::kInternal:
    case absl::StatusCode::kUnknown:
    case absl::StatusCode::kDeadlineExceeded:
      return true;
    default:
      return false;
  }
}

// A new-session open that may succeed when tried again (server restarting,
// loading or draining).
bool IsRetryableOpenError(const absl::Status& status) {
  switch (status.code()) {
    case absl::StatusCode::kUnavailable:
    case absl::StatusCode::kCancelled:
    case absl::StatusCode::kAborted:
    case absl::StatusCode::kUnknown:
    case absl::StatusCode::kInternal:
      return true;
    default:
      return false;
  }
}

std::string DescribeUnreachable(const absl::Status& status, const std::string& target) {
  return absl::StrCat("cannot reach the FrameDiffuser server at ", target, ": ", status.message());
}

}  // namespace

std::string NewRoutingKey() {
  thread_local std::mt19937_64 rng([] {
    std::random_device device;
    return (uint64_t(device()) << 32) ^ device();
  }());
  static constexpr char kHex[] = "0123456789abcdef";
  std::string key(32, '0');
  for (int half = 0; half < 2; ++half) {
    uint64_t bits = rng();
    for (int i = 0; i < 16; ++i, bits >>= 4) key[half * 16 + i] = kHex[bits & 0xf];
  }
  return key;
}

SessionImpl::SessionImpl(std::shared_ptr<Connection> connection, const SessionOptions& options)
    : connection_(std::move(connection)), options_(options) {
  options_.keyframe = ImageView();
  options_.keyframe_basecolor = ImageView();
}

absl::StatusOr<std::unique_ptr<SessionImpl>> SessionImpl::Open(
    std::shared_ptr<Connection> connection, const SessionOptions& options) {
  if (options.environment.empty()) {
    return absl::InvalidArgumentError("open.environment: required (see ListEnvironments)");
  }
  std::unique_ptr<SessionImpl> session(new SessionImpl(std::move(connection), options));
  v1::OpenSession* open = session->open_request_.mutable_open();
  open->set_environment(options.environment);
  open->set_width(options.width);
  open->set_height(options.height);
  open->set_seed(options.seed);
  open->set_steps(options.steps);
  open->set_scheduler(internal::ToWire(options.scheduler));
  open->set_sky_mode(internal::ToWire(options.sky_mode));
  open->set_output_dtype(internal::ToWire(options.output_dtype));
  open->set_output_compression(internal::ToWire(options.output_compression));
  open->set_max_frames_in_flight(options.max_frames_in_flight);
  if (!options.keyframe.empty()) {
    if (absl::Status s =
            FillImage(options.keyframe, 3, options.width, options.height, "open.keyframe",
                      options.input_compression, options.zstd_level, open->mutable_keyframe());
        !s.ok()) {
      return s;
    }
  }
  if (!options.keyframe_basecolor.empty()) {
    if (absl::Status s = FillImage(options.keyframe_basecolor, 3, options.width, options.height,
                                   "open.keyframe_basecolor", options.input_compression,
                                   options.zstd_level, open->mutable_keyframe_basecolor());
        !s.ok()) {
      return s;
    }
  }
  absl::StatusOr<Opened> opened =
      session->Handshake(session->open_request_, NewRoutingKey(),
                         absl::Now() + options.open_timeout, /*wait_for_ready=*/false);
  if (!opened.ok()) {
    if (opened.status().code() == absl::StatusCode::kUnavailable) {
      return absl::UnavailableError(
          DescribeUnreachable(opened.status(), session->connection_->options().target));
    }
    return opened.status();
  }
  {
    std::lock_guard<std::mutex> write_lock(session->write_mu_);
    std::lock_guard<std::mutex> lock(session->mu_);
    session->InstallLocked(std::move(*opened));
  }
  session->receiver_ = std::thread([s = session.get()] { s->ReceiverLoop(); });
  return session;
}

SessionImpl::~SessionImpl() {
  {
    std::lock_guard<std::mutex> lock(mu_);
    shutting_down_ = true;
    if (call_ != nullptr) call_->context.TryCancel();
    if (handshake_context_ != nullptr) handshake_context_->TryCancel();
  }
  cv_.notify_all();
  if (receiver_.joinable()) receiver_.join();
}

std::string SessionImpl::session_id() const {
  std::lock_guard<std::mutex> lock(mu_);
  return session_id_;
}

SessionSettings SessionImpl::settings() const {
  std::lock_guard<std::mutex> lock(mu_);
  return settings_;
}

uint32_t SessionImpl::frames_in_flight() const {
  std::lock_guard<std::mutex> lock(mu_);
  return window_;
}

int SessionImpl::failover_count() const {
  std::lock_guard<std::mutex> lock(mu_);
  return failover_count_;
}

absl::StatusOr<SessionImpl::Opened> SessionImpl::Handshake(const Request& first,
                                                           const std::string& routing_key,
                                                           absl::Time deadline,
                                                           bool wait_for_ready) {
  auto call = std::make_shared<Call>();
  connection_->Prepare(&call->context);
  call->context.AddMetadata("x-session-id", routing_key);
  call->context.set_wait_for_ready(wait_for_ready);
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (shutting_down_) return absl::CancelledError("session destroyed");
    handshake_context_ = &call->context;
  }
  CallWatchdog watchdog(&call->context, deadline);
  absl::Status protocol_error;
  std::optional<v1::SessionNotice> notice;
  call->stream = connection_->stub()->Render(&call->context);
  if (call->stream->Write(first)) {
    Response response;
    while (call->stream->Read(&response)) {
      if (response.has_notice()) {
        notice = response.notice();
        continue;
      }
      if (response.has_opened()) {
        watchdog.Disarm();
        std::lock_guard<std::mutex> lock(mu_);
        handshake_context_ = nullptr;
        if (shutting_down_) {
          call->context.TryCancel();
          return absl::CancelledError("session destroyed");
        }
        return Opened{std::move(call), std::move(*response.mutable_opened())};
      }
      protocol_error = absl::InternalError(
          "protocol error: the server answered the first message with something other than "
          "SessionOpened");
      call->context.TryCancel();
      break;
    }
  }
  const grpc::Status finished = call->stream->Finish();
  watchdog.Disarm();
  {
    std::lock_guard<std::mutex> lock(mu_);
    handshake_context_ = nullptr;
  }
  if (!protocol_error.ok()) return protocol_error;
  absl::Status status = FromGrpc(finished);
  if (watchdog.fired()) {
    return absl::DeadlineExceededError(
        absl::StrCat("no SessionOpened from ", connection_->options().target, " in time",
                     status.ok() ? "" : absl::StrCat(": ", status.message())));
  }
  if (status.ok()) {
    status = absl::UnavailableError("the server ended the stream before SessionOpened");
  }
  if (notice.has_value() && !notice->message().empty()) {
    status =
        absl::Status(status.code(), absl::StrCat(status.message(), " (",
                                                 v1::SessionNotice::Reason_Name(notice->reason()),
                                                 ": ", notice->message(), ")"));
  }
  return status;
}

void SessionImpl::InstallLocked(Opened opened) {
  call_ = std::move(opened.call);
  session_id_ = opened.opened.session_id();
  resume_token_ = opened.opened.resume_token();
  if (!opened.opened.resumed()) {
    settings_ = internal::FromWire(opened.opened.settings());
    uint32_t window = std::max<uint32_t>(options_.max_frames_in_flight, 1);
    if (settings_.max_frames_in_flight > 0)
      window = std::min(window, settings_.max_frames_in_flight);
    window_ = window;
  }
  sent_ = 0;  // everything unanswered goes out again on the new call
  last_notice_.reset();
  state_ = State::kStreaming;
  cv_.notify_all();
}

absl::Status SessionImpl::Submit(const FrameRequest& request, Session::FrameCallback done) {
  uint32_t width, height;
  {
    std::lock_guard<std::mutex> lock(mu_);
    width = settings_.width;
    height = settings_.height;
  }
  // Copy the caller's pixels into the request (the one copy), unlocked.
  auto message = std::make_shared<Request>();
  v1::FrameInput* frame = message->mutable_frame();
  frame->set_frame_index(request.frame_index);
  const Compression compression = options_.input_compression;
  const int level = options_.zstd_level;
  v1::GBuffer* gbuffer = frame->mutable_gbuffer();
  struct Field {
    const ImageView* view;
    int channels;
    const char* name;
    v1::Image* out;
    bool required;
  };
  const Field fields[] = {
      {&request.gbuffer.basecolor, 3, "frame.gbuffer.basecolor", gbuffer->mutable_basecolor(),
       true},
      {&request.gbuffer.normals, 3, "frame.gbuffer.normals", gbuffer->mutable_normals(), true},
      {&request.gbuffer.depth, 1, "frame.gbuffer.depth", gbuffer->mutable_depth(), true},
      {&request.gbuffer.roughness, 1, "frame.gbuffer.roughness", gbuffer->mutable_roughness(),
       true},
  };
  for (const Field& field : fields) {
    if (absl::Status s = FillImage(*field.view, field.channels, width, height, field.name,
                                   compression, level, field.out);
        !s.ok()) {
      return s;
    }
  }
  const struct {
    const ImageView* view;
    int channels;
    const char* name;
    std::function<v1::Image*()> out;
  } optional_fields[] = {
      {&request.gbuffer.metallic, 1, "frame.gbuffer.metallic",
       [&] { return gbuffer->mutable_metallic(); }},
      {&request.sky, 3, "frame.sky", [&] { return frame->mutable_sky(); }},
      {&request.keyframe, 3, "frame.keyframe", [&] { return frame->mutable_keyframe(); }},
      {&request.keyframe_basecolor, 3, "frame.keyframe_basecolor",
       [&] { return frame->mutable_keyframe_basecolor(); }},
  };
  for (const auto& field : optional_fields) {
    if (field.view->empty()) continue;
    if (absl::Status s = FillImage(*field.view, field.channels, width, height, field.name,
                                   compression, level, field.out());
        !s.ok()) {
      return s;
    }
  }

  {
    std::unique_lock<std::mutex> lock(mu_);
    auto check = [&]() -> absl::Status {
      if (state_ == State::kDone) {
        return failure_.ok() ? absl::FailedPreconditionError("the session is closed") : failure_;
      }
      if (close_requested_) return absl::FailedPreconditionError("the session is closing");
      // Above the last rendered or outstanding frame; a rejected frame's
      // index may be used again (the server did not advance).
      std::optional<uint64_t> floor = last_received_index_;
      if (!pending_.empty()) floor = std::max(floor.value_or(0), pending_.back().frame_index);
      if (floor.has_value() && request.frame_index <= *floor) {
        return absl::FailedPreconditionError(
            absl::StrCat("frame.frame_index: ", request.frame_index,
                         " must be greater than the previous frame's ", *floor));
      }
      return absl::OkStatus();
    };
    if (absl::Status s = check(); !s.ok()) return s;
    cv_.wait(lock, [&] {
      return state_ == State::kDone || close_requested_ || pending_.size() < window_;
    });
    if (absl::Status s = check(); !s.ok()) return s;  // things may have changed while waiting
    pending_.push_back(Pending{request.frame_index, std::move(message), std::move(done)});
  }
  Pump();
  return absl::OkStatus();
}

void SessionImpl::Pump() {
  std::lock_guard<std::mutex> write_lock(write_mu_);
  for (;;) {
    std::shared_ptr<const Request> request;
    std::shared_ptr<Call> call;
    {
      std::lock_guard<std::mutex> lock(mu_);
      if (state_ != State::kStreaming || sent_ >= pending_.size()) return;
      request = pending_[sent_].request;
      call = call_;
      ++sent_;
    }
    // A failed write means the stream broke: the receiver notices and
    // failover re-sends every unanswered frame.
    if (!call->stream->Write(*request)) return;
  }
}

absl::Status SessionImpl::Close() {
  if (receiver_.get_id() == std::this_thread::get_id()) {
    return absl::FailedPreconditionError("Session::Close called from a frame callback");
  }
  for (;;) {
    {
      std::unique_lock<std::mutex> lock(mu_);
      close_requested_ = true;
      cv_.notify_all();  // wakes Submits waiting for a slot: they fail now
      cv_.wait(lock, [&] {
        return state_ == State::kDone || (state_ == State::kStreaming && pending_.empty());
      });
      if (state_ == State::kDone) break;
    }
    std::lock_guard<std::mutex> write_lock(write_mu_);
    std::shared_ptr<Call> call;
    {
      std::lock_guard<std::mutex> lock(mu_);
      // Recovery may have begun between the two locks: wait for it.
      if (state_ != State::kStreaming || !pending_.empty()) continue;
      call = call_;
    }
    call->stream->WritesDone();  // the server closes the session and ends the stream
    break;
  }
  if (receiver_.joinable()) receiver_.join();
  std::lock_guard<std::mutex> lock(mu_);
  return failure_;
}

void SessionImpl::ReceiverLoop() {
  for (;;) {
    std::shared_ptr<Call> call;
    {
      std::lock_guard<std::mutex> lock(mu_);
      call = call_;
    }
    absl::Status protocol_error;
    Response response;
    while (call->stream->Read(&response)) {
      protocol_error = HandleResponse(&response);
      if (!protocol_error.ok()) {
        call->context.TryCancel();
        break;
      }
    }
    const grpc::Status finished = call->stream->Finish();
    absl::Status cause = protocol_error.ok() ? FromGrpc(finished) : protocol_error;
    bool give_up = false;
    {
      std::lock_guard<std::mutex> lock(mu_);
      if (shutting_down_) {
        cause = absl::CancelledError("session destroyed");
        give_up = true;
      } else if (close_requested_ && pending_.empty()) {
        // Every frame was answered; whatever happened after the half-close
        // does not matter to the caller.
        state_ = State::kDone;
        failure_ = absl::OkStatus();
        cv_.notify_all();
        return;
      } else if (!protocol_error.ok()) {
        give_up = true;  // a misbehaving server: failing over would not help
      } else {
        if (cause.ok()) {
          cause =
              absl::UnavailableError("the server ended the stream before the session was closed");
        }
        state_ = State::kRecovering;
      }
    }
    if (!give_up) cause = Recover(cause);
    if (!cause.ok()) {
      FailAll(cause);
      return;
    }
  }
}

absl::Status SessionImpl::HandleResponse(Response* response) {
  if (response->has_notice()) {
    std::lock_guard<std::mutex> lock(mu_);
    last_notice_ = response->notice();
    return absl::OkStatus();
  }
  if (!response->has_frame() && !response->has_frame_error()) {
    return absl::InternalError("protocol error: unexpected message on an open session stream");
  }
  const uint64_t index = response->has_frame() ? response->frame().frame_index()
                                               : response->frame_error().frame_index();
  uint32_t width, height;
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (pending_.empty() || sent_ == 0 || pending_.front().frame_index != index) {
      return absl::InternalError(absl::StrCat(
          "protocol error: the server answered frame ", index,
          pending_.empty() ? std::string(" with no frame outstanding")
                           : absl::StrCat(", expected frame ", pending_.front().frame_index)));
    }
    width = settings_.width;
    height = settings_.height;
  }
  absl::StatusOr<Frame> result;
  std::shared_ptr<const std::string> pixels;
  v1::Image shape;
  if (response->has_frame()) {
    v1::RenderedFrame* rendered = response->mutable_frame();
    v1::Image* image = rendered->mutable_image();
    if (image->width() != width || image->height() != height || image->channels() != 3) {
      return absl::InternalError(absl::StrCat(
          "protocol error: frame ", index, " is ", image->width(), "x", image->height(), "x",
          image->channels(), ", expected ", width, "x", height, "x3"));
    }
    absl::StatusOr<std::string> bytes = internal::TakeImageBytes(image, "frame.image");
    if (!bytes.ok()) return bytes.status();
    pixels = std::make_shared<const std::string>(std::move(*bytes));
    shape.set_width(image->width());
    shape.set_height(image->height());
    shape.set_channels(image->channels());
    shape.set_dtype(image->dtype());
    Frame frame;
    frame.frame_index = index;
    frame.width = static_cast<int>(image->width());
    frame.height = static_cast<int>(image->height());
    frame.channels = static_cast<int>(image->channels());
    frame.dtype = *internal::FromWire(image->dtype());  // checked by TakeImageBytes
    frame.data = pixels;
    frame.timings = internal::FromWire(rendered->timings());
    result = std::move(frame);
  } else {
    const v1::FrameError& error = response->frame_error();
    result = absl::Status(
        internal::CodeFromInt(error.code()),
        error.message().empty() ? absl::StrCat("frame ", index, " rejected") : error.message());
    if (result.status().ok()) result = absl::UnknownError("FrameError with code OK");
  }
  Pending answered;
  {
    std::lock_guard<std::mutex> lock(mu_);
    answered = std::move(pending_.front());
    pending_.pop_front();
    --sent_;
    if (pixels != nullptr) {
      // The new "previous frame" that failover continues from.
      last_received_index_ = index;
      last_output_ = pixels;
      last_output_shape_ = std::move(shape);
      last_answered_request_ = answered.request;
    }
    cv_.notify_all();
  }
  if (answered.done) answered.done(std::move(result));
  return absl::OkStatus();
}

SessionImpl::Request SessionImpl::BuildFailoverOpen() const {
  Request request = open_request_;
  v1::OpenSession* open = request.mutable_open();
  // Same size and seed as the session in effect, so the new one continues it.
  open->set_width(settings_.width);
  open->set_height(settings_.height);
  open->set_seed(settings_.seed);
  if (last_output_ != nullptr) {
    ImageView view = internal::ViewOfBytes(*last_output_, last_output_shape_);
    // Cannot fail: the shape was checked when the frame arrived.
    (void)FillImage(view, 3, settings_.width, settings_.height, "open.keyframe",
                    options_.input_compression, options_.zstd_level, open->mutable_keyframe());
    if (last_answered_request_ != nullptr) {
      *open->mutable_keyframe_basecolor() = last_answered_request_->frame().gbuffer().basecolor();
    }
  }
  return request;
}

absl::Status SessionImpl::Recover(const absl::Status& cause) {
  FailoverEvent event;
  Request resume;
  Request open;
  bool try_resume;
  std::optional<uint64_t> last_received;
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (!options_.failover || !IsFailoverCause(cause, last_notice_)) return cause;
    event.cause = cause;
    event.old_session_id = session_id_;
    event.last_frame_index = last_received_index_;
    last_received = last_received_index_;
    // A draining server drops its sessions: resuming there cannot work.
    try_resume = !IsNotice(last_notice_, v1::SessionNotice::REASON_DRAINING) &&
                 !IsNotice(last_notice_, v1::SessionNotice::REASON_EVICTED);
    resume.mutable_resume()->set_session_id(session_id_);
    resume.mutable_resume()->set_resume_token(resume_token_);
    open = BuildFailoverOpen();
    last_notice_.reset();
  }
  const absl::Time deadline = absl::Now() + options_.failover_timeout;

  std::optional<Opened> opened;
  if (try_resume) {
    // Right after a connection broke, a new call can still be placed on the
    // dying transport and fail with UNAVAILABLE ("Socket closed", "Broken
    // pipe") without reaching any server; the next call gets a fresh
    // connection. So UNAVAILABLE is tried again a few times before resuming
    // is given up for a new session; other codes (NOT_FOUND,
    // PERMISSION_DENIED, ...) are the server's final answer.
    absl::StatusOr<Opened> resumed;
    absl::Duration resume_backoff = absl::Milliseconds(50);
    for (int attempt = 1;; ++attempt) {
      resumed = Handshake(resume, event.old_session_id, deadline, /*wait_for_ready=*/true);
      if (resumed.ok() || resumed.status().code() != absl::StatusCode::kUnavailable ||
          attempt >= kResumeAttempts || absl::Now() + resume_backoff >= deadline) {
        break;
      }
      std::unique_lock<std::mutex> lock(mu_);
      if (cv_.wait_for(lock, absl::ToChronoNanoseconds(resume_backoff),
                       [this] { return shutting_down_; })) {
        return absl::CancelledError("session destroyed");
      }
      resume_backoff *= 2;
    }
    if (resumed.ok()) {
      const v1::SessionOpened& info = resumed->opened;
      const bool same_state = info.resumed() && (info.has_last_frame_index()
                                                     ? last_received.has_value() &&
                                                           *last_received == info.last_frame_index()
                                                     : !last_received.has_value());
      if (same_state) {
        opened = std::move(*resumed);
        event.resumed = true;
      } else {
        // The server rendered frames whose answers were lost: that session is
        // ahead of us. Close it (half-close) and start over from our last frame.
        resumed->call->stream->WritesDone();
        CallWatchdog bound(&resumed->call->context,
                           std::min(deadline, absl::Now() + absl::Seconds(2)));
        (void)resumed->call->stream->Finish();
      }
    }
  }
  // A new session from the last received frame, retried while the server is
  // restarting, until the deadline.
  absl::Duration backoff = absl::Milliseconds(50);
  while (!opened.has_value()) {
    absl::StatusOr<Opened> fresh =
        Handshake(open, NewRoutingKey(), deadline, /*wait_for_ready=*/true);
    if (fresh.ok()) {
      opened = std::move(*fresh);
      break;
    }
    std::unique_lock<std::mutex> lock(mu_);
    if (shutting_down_) return absl::CancelledError("session destroyed");
    if (!IsRetryableOpenError(fresh.status()) || absl::Now() + backoff >= deadline) {
      return absl::Status(
          fresh.status().code(),
          absl::StrCat("failover failed (the stream broke with ",
                       absl::StatusCodeToString(cause.code()), ": ", cause.message(),
                       "); opening a new session: ", fresh.status().message()));
    }
    // Back off before the next attempt (woken early only by ~SessionImpl).
    cv_.wait_for(lock, absl::ToChronoNanoseconds(backoff), [this] { return shutting_down_; });
    backoff = std::min(backoff * 2, absl::Seconds(1));
  }

  {
    std::lock_guard<std::mutex> write_lock(write_mu_);
    std::lock_guard<std::mutex> lock(mu_);
    if (shutting_down_) {
      opened->call->context.TryCancel();
      return absl::CancelledError("session destroyed");
    }
    event.new_session_id = opened->opened.session_id();
    event.resent_frames = static_cast<int>(pending_.size());
    InstallLocked(std::move(*opened));
    ++failover_count_;
  }
  Pump();
  if (options_.on_failover) options_.on_failover(event);
  return absl::OkStatus();
}

void SessionImpl::FailAll(const absl::Status& status) {
  std::deque<Pending> failed;
  {
    std::lock_guard<std::mutex> lock(mu_);
    state_ = State::kDone;
    failure_ = status;
    failed.swap(pending_);
    sent_ = 0;
    cv_.notify_all();
  }
  for (Pending& pending : failed) {
    if (pending.done) pending.done(status);
  }
}

}  // namespace fd::client

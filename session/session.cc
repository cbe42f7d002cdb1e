#include "session/session.h"

#include <utility>

#include "absl/strings/str_cat.h"
#include "session/frame_seed.h"
#include "session/state_blob.h"
#include "session/string_view_compat.h"

namespace fd::session {

Session::Session(std::string id, std::string client_identity, SessionState state,
                 const Clock* clock)
    : id_(std::move(id)),
      client_identity_(std::move(client_identity)),
      settings_(state.settings()),
      clock_(clock),
      state_(std::move(state)),
      last_activity_(clock->Now()) {}

absl::Status Session::TryBeginFrame(uint64_t frame_index, std::optional<Keyframe> reseed) {
  absl::MutexLock lock(&mu_);
  if (end_reason_.has_value() && *end_reason_ != EndReason::kDraining) {
    return absl::FailedPreconditionError(
        absl::StrCat("session ", id_, " has ended (", ToAbsl(EndReasonName(*end_reason_)), ")"));
  }
  if (in_flight_.has_value()) {
    return absl::FailedPreconditionError(
        absl::StrCat("frame_index ", frame_index, ": frame ", *in_flight_,
                     " of this session is still in flight (one frame at a time)"));
  }
  if (state_.last_frame_index().has_value() && frame_index <= *state_.last_frame_index()) {
    return absl::FailedPreconditionError(
        absl::StrCat("frame_index: must be greater than the last rendered frame's (",
                     *state_.last_frame_index(), "), got ", frame_index));
  }
  if (reseed.has_value()) {
    absl::Status valid = state_.CheckImage("keyframe", reseed->frame, /*allow_empty=*/false);
    if (!valid.ok()) return valid;
    valid = state_.CheckImage("keyframe_basecolor", reseed->basecolor, /*allow_empty=*/true);
    if (!valid.ok()) return valid;
  }
  in_flight_ = frame_index;
  in_flight_reseed_ = std::move(reseed);
  last_activity_ = clock_->Now();
  return absl::OkStatus();
}

absl::Status Session::CheckInFlight(uint64_t frame_index) const {
  if (!in_flight_.has_value()) {
    return absl::FailedPreconditionError(
        absl::StrCat("frame_index ", frame_index, ": no frame of session ", id_, " is in flight"));
  }
  if (*in_flight_ != frame_index) {
    return absl::FailedPreconditionError(
        absl::StrCat("frame_index ", frame_index, ": the frame in flight is ", *in_flight_));
  }
  return absl::OkStatus();
}

absl::Status Session::ReadFrameContext(uint64_t frame_index,
                                       absl::FunctionRef<void(const FrameContext&)> fn) const {
  absl::ReaderMutexLock lock(&mu_);
  absl::Status in_flight = CheckInFlight(frame_index);
  if (!in_flight.ok()) return in_flight;
  FrameContext context;
  context.frame_index = frame_index;
  context.frame_counter = state_.frame_counter();
  context.frame_seed = FrameSeed(settings_.seed, state_.frame_counter());
  if (in_flight_reseed_.has_value()) {
    context.previous_frame = in_flight_reseed_->frame;
    context.previous_basecolor = in_flight_reseed_->basecolor;
    context.reseeded = true;
  } else {
    context.previous_frame = state_.previous_frame();
    context.previous_basecolor = state_.previous_basecolor();
    context.previous_latent = state_.previous_latent();
  }
  fn(context);
  return absl::OkStatus();
}

absl::Status Session::CommitFrame(uint64_t frame_index, ImageBuffer output, ImageBuffer basecolor,
                                  LatentBuffer latent) {
  absl::MutexLock lock(&mu_);
  absl::Status in_flight = CheckInFlight(frame_index);
  if (!in_flight.ok()) return in_flight;
  absl::Status committed =
      state_.CommitFrame(frame_index, std::move(output), std::move(basecolor), std::move(latent));
  if (!committed.ok()) return committed;
  in_flight_.reset();
  in_flight_reseed_.reset();
  last_activity_ = clock_->Now();
  return absl::OkStatus();
}

absl::Status Session::AbortFrame(uint64_t frame_index) {
  absl::MutexLock lock(&mu_);
  absl::Status in_flight = CheckInFlight(frame_index);
  if (!in_flight.ok()) return in_flight;
  in_flight_.reset();
  in_flight_reseed_.reset();
  last_activity_ = clock_->Now();
  return absl::OkStatus();
}

std::optional<uint64_t> Session::frame_in_flight() const {
  absl::ReaderMutexLock lock(&mu_);
  return in_flight_;
}

std::optional<uint64_t> Session::last_frame_index() const {
  absl::ReaderMutexLock lock(&mu_);
  return state_.last_frame_index();
}

uint64_t Session::frame_counter() const {
  absl::ReaderMutexLock lock(&mu_);
  return state_.frame_counter();
}

void Session::Touch() {
  absl::MutexLock lock(&mu_);
  last_activity_ = clock_->Now();
}

absl::Time Session::last_activity() const {
  absl::ReaderMutexLock lock(&mu_);
  return last_activity_;
}

bool Session::IsIdle(absl::Time now, absl::Duration timeout) const {
  absl::ReaderMutexLock lock(&mu_);
  return !in_flight_.has_value() && now - last_activity_ >= timeout;
}

std::optional<EndReason> Session::end_reason() const {
  absl::ReaderMutexLock lock(&mu_);
  return end_reason_;
}

void Session::SetClosePending(bool pending) {
  absl::MutexLock lock(&mu_);
  close_pending_ = pending;
}

bool Session::close_pending() const {
  absl::ReaderMutexLock lock(&mu_);
  return close_pending_;
}

bool Session::MarkEnded(EndReason reason) {
  absl::MutexLock lock(&mu_);
  if (end_reason_.has_value()) return false;
  end_reason_ = reason;
  return true;
}

bool Session::MarkEndedIfIdle(absl::Time now, absl::Duration timeout, EndReason reason) {
  absl::MutexLock lock(&mu_);
  if (end_reason_.has_value() || in_flight_.has_value() || now - last_activity_ < timeout) {
    return false;
  }
  end_reason_ = reason;
  return true;
}

SessionState Session::StateSnapshot() const {
  absl::ReaderMutexLock lock(&mu_);
  return state_;
}

absl::StatusOr<std::string> Session::ExportState() const {
  absl::ReaderMutexLock lock(&mu_);
  return fd::session::ExportState(state_);
}

size_t Session::MemoryBytes() const {
  absl::ReaderMutexLock lock(&mu_);
  size_t bytes = state_.MemoryBytes();
  if (in_flight_reseed_.has_value()) {
    bytes += in_flight_reseed_->frame.size_bytes() + in_flight_reseed_->basecolor.size_bytes();
  }
  return bytes;
}

}  // namespace fd::session

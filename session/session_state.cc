#include "session/session_state.h"

#include <utility>

#include "absl/strings/str_cat.h"
#include "session/frame_seed.h"
#include "session/string_view_compat.h"

namespace fd::session {

absl::StatusOr<SessionState> SessionState::StartFromKeyframe(SessionSettings settings,
                                                             ImageBuffer keyframe,
                                                             ImageBuffer keyframe_basecolor) {
  absl::Status valid = ValidateSessionSettings(settings);
  if (!valid.ok()) return valid;
  SessionState state;
  state.settings_ = std::move(settings);
  state.start_mode_ = StartMode::kKeyframe;
  valid = state.CheckImage("keyframe", keyframe, /*allow_empty=*/false);
  if (!valid.ok()) return valid;
  valid = state.CheckImage("keyframe_basecolor", keyframe_basecolor, /*allow_empty=*/true);
  if (!valid.ok()) return valid;
  state.previous_frame_ = std::move(keyframe);
  state.previous_basecolor_ = std::move(keyframe_basecolor);
  return state;
}

absl::StatusOr<SessionState> SessionState::StartFromGBufferOnly(SessionSettings settings) {
  absl::Status valid = ValidateSessionSettings(settings);
  if (!valid.ok()) return valid;
  SessionState state;
  state.settings_ = std::move(settings);
  state.start_mode_ = StartMode::kGBufferOnly;
  return state;
}

absl::StatusOr<SessionState> SessionState::Restore(SessionSettings settings, StartMode start_mode,
                                                   uint64_t frame_counter,
                                                   std::optional<uint64_t> last_frame_index,
                                                   ImageBuffer previous_frame,
                                                   ImageBuffer previous_basecolor) {
  absl::Status valid = ValidateSessionSettings(settings);
  if (!valid.ok()) return valid;
  if (!IsValidStartMode(static_cast<uint8_t>(start_mode))) {
    return absl::InvalidArgumentError(
        absl::StrCat("start_mode: invalid value ", static_cast<int>(start_mode)));
  }
  SessionState state;
  state.settings_ = std::move(settings);
  state.start_mode_ = start_mode;
  valid = state.CheckImage("previous_frame", previous_frame, /*allow_empty=*/true);
  if (!valid.ok()) return valid;
  valid = state.CheckImage("previous_basecolor", previous_basecolor, /*allow_empty=*/true);
  if (!valid.ok()) return valid;
  const bool needs_previous_frame = start_mode == StartMode::kKeyframe || frame_counter > 0;
  if (needs_previous_frame && previous_frame.empty()) {
    return absl::InvalidArgumentError(
        absl::StrCat("previous_frame: required (start_mode ", ToAbsl(StartModeName(start_mode)),
                     ", frame_counter ", frame_counter, ") but empty"));
  }
  if (previous_frame.empty() && !previous_basecolor.empty()) {
    return absl::InvalidArgumentError("previous_basecolor: present without a previous_frame");
  }
  if (last_frame_index.has_value() != (frame_counter > 0)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "last_frame_index: must be present exactly when frames were rendered (frame_counter ",
        frame_counter, ", last_frame_index ", last_frame_index.has_value() ? "present" : "absent",
        ")"));
  }
  state.frame_counter_ = frame_counter;
  state.last_frame_index_ = last_frame_index;
  state.previous_frame_ = std::move(previous_frame);
  state.previous_basecolor_ = std::move(previous_basecolor);
  return state;
}

bool operator==(const LatentBuffer& a, const LatentBuffer& b) {
  if (a.empty() || b.empty()) return a.empty() == b.empty();
  return a.channels == b.channels && a.height == b.height && a.width == b.width &&
         a.source == b.source && *a.values == *b.values;
}

absl::Status SessionState::CommitFrame(uint64_t frame_index, ImageBuffer output,
                                       ImageBuffer basecolor, LatentBuffer latent) {
  if (last_frame_index_.has_value() && frame_index <= *last_frame_index_) {
    return absl::FailedPreconditionError(
        absl::StrCat("frame_index: must be greater than the last rendered frame's (",
                     *last_frame_index_, "), got ", frame_index));
  }
  absl::Status valid = CheckImage("output", output, /*allow_empty=*/false);
  if (!valid.ok()) return valid;
  valid = CheckImage("basecolor", basecolor, /*allow_empty=*/false);
  if (!valid.ok()) return valid;
  if (!latent.empty() && latent.values->size() !=
                             static_cast<size_t>(latent.channels) * latent.height * latent.width) {
    return absl::InvalidArgumentError(absl::StrCat("latent: ", latent.values->size(),
                                                   " values for a ", latent.channels, " x ",
                                                   latent.height, " x ", latent.width, " latent"));
  }
  previous_frame_ = std::move(output);
  previous_basecolor_ = std::move(basecolor);
  previous_latent_ = std::move(latent);
  ++frame_counter_;
  last_frame_index_ = frame_index;
  return absl::OkStatus();
}

uint64_t SessionState::NextFrameSeed() const { return FrameSeed(settings_.seed, frame_counter_); }

size_t SessionState::ImageBytes() const {
  return static_cast<size_t>(settings_.width) * settings_.height * 3;
}

size_t SessionState::MemoryBytes() const {
  size_t bytes = sizeof(*this) + previous_frame_.size_bytes() + previous_basecolor_.size_bytes() +
                 previous_latent_.size_bytes();
  // A short environment name lives inside the std::string (SSO); count the
  // heap block only when there is one.
  if (settings_.environment.capacity() > std::string().capacity()) {
    bytes += settings_.environment.capacity() + 1;
  }
  return bytes;
}

absl::Status SessionState::CheckImage(const char* field, const ImageBuffer& pixels,
                                      bool allow_empty) const {
  if (pixels.empty() && allow_empty) return absl::OkStatus();
  if (pixels.size_bytes() != ImageBytes() || pixels.empty()) {
    return absl::InvalidArgumentError(absl::StrCat(field, ": expected ", ImageBytes(), " bytes (",
                                                   settings_.width, " x ", settings_.height,
                                                   " x 3 uint8), got ", pixels.size_bytes()));
  }
  if (pixels.width() != settings_.width || pixels.height() != settings_.height ||
      pixels.channels() != 3 || pixels.type() != PixelType::kUint8) {
    return absl::InvalidArgumentError(
        absl::StrCat(field, ": expected ", settings_.width, " x ", settings_.height,
                     " x 3 uint8, got ", pixels.width(), " x ", pixels.height(), " x ",
                     pixels.channels(), " ", ToAbsl(PixelTypeName(pixels.type()))));
  }
  return absl::OkStatus();
}

bool operator==(const SessionState& a, const SessionState& b) {
  return a.settings_ == b.settings_ && a.start_mode_ == b.start_mode_ &&
         a.frame_counter_ == b.frame_counter_ && a.last_frame_index_ == b.last_frame_index_ &&
         a.previous_frame_ == b.previous_frame_ && a.previous_basecolor_ == b.previous_basecolor_ &&
         a.previous_latent_ == b.previous_latent_;
}

}  // namespace fd::session

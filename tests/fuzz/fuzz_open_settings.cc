// Fuzz target: the bytes of a wire RenderRequest as the first message of a
// stream -> what StreamController does with an OpenSession (settings resolved
// against an environment and the server's limits, the start keyframe decoded,
// the session state started) or a ResumeSession (id checked, the store asked).
//
// Input: a serialized framediffuser.v1.RenderRequest.
// Properties: resolved settings are within the limits and the environment's
// samplers; a started state has the resolved size; every error has a code
// the proto documents for opening, names its field and is bounded in size.
#include <cstddef>
#include <cstdint>
#include <memory>

#include "framediffuser/v1/render_service.pb.h"
#include "server/frame_input.h"
#include "server/open_settings.h"
#include "session/clock.h"
#include "session/random_token.h"
#include "session/session_state.h"
#include "session/session_store.h"
#include "tests/fuzz/fuzz_check.h"

namespace {

namespace v1 = ::framediffuser::v1;
using fd::session::SchedulerKind;

// A small environment: 16x16 native, two samplers; limits 8..32.
fd::session::EnvironmentInfo FuzzEnvironment() {
  fd::session::EnvironmentInfo env;
  env.name = "street";
  env.native_width = 16;
  env.native_height = 16;
  env.default_steps = 4;
  env.default_scheduler = SchedulerKind::kUniPC;
  env.default_sky_mode = fd::session::SkyMode::kOff;
  env.schedulers = {SchedulerKind::kUniPC, SchedulerKind::kDDIM};
  env.readiness = fd::session::Readiness::kReady;
  return env;
}

fd::server::SessionLimits FuzzLimits() {
  fd::server::SessionLimits limits;
  limits.min_size = 8;
  limits.max_size = 32;
  limits.max_steps = 8;
  limits.max_frames_in_flight = 2;
  return limits;
}

void Open(const v1::OpenSession& open) {
  static const fd::session::EnvironmentInfo env = FuzzEnvironment();
  static const fd::server::SessionLimits limits = FuzzLimits();
  absl::StatusOr<fd::session::SessionSettings> settings =
      fd::server::ResolveOpenSettings(open, env, limits, /*random_seed=*/7);
  if (!settings.ok()) {
    fd::fuzz::CheckError(settings.status(), absl::StatusCode::kInvalidArgument, "open");
    return;
  }
  FD_FUZZ_CHECK(settings->width >= limits.min_size && settings->width <= limits.max_size, "width");
  FD_FUZZ_CHECK(settings->height >= limits.min_size && settings->height <= limits.max_size,
                "height");
  FD_FUZZ_CHECK(settings->width % 8 == 0 && settings->height % 8 == 0, "multiple of 8");
  FD_FUZZ_CHECK(settings->steps >= 1 && settings->steps <= limits.max_steps, "steps");
  FD_FUZZ_CHECK(settings->max_frames_in_flight >= 1 &&
                    settings->max_frames_in_flight <= limits.max_frames_in_flight,
                "frames in flight");
  FD_FUZZ_CHECK(settings->seed != 0, "seed");
  FD_FUZZ_CHECK(fd::session::ValidateSessionSettings(*settings).ok(), "valid settings");
  // The wire form round-trips what the client asked for (fields it set).
  const v1::SessionSettings wire = fd::server::ToWireSettings(*settings, false);
  FD_FUZZ_CHECK(wire.width() == settings->width && wire.steps() == settings->steps, "wire form");

  absl::StatusOr<std::optional<fd::server::DecodedStartKeyframe>> keyframe =
      fd::server::DecodeOpenKeyframe(open, settings->width, settings->height);
  if (!keyframe.ok()) {
    fd::fuzz::CheckError(keyframe.status(), absl::StatusCode::kInvalidArgument, "open.keyframe");
    return;
  }
  absl::StatusOr<fd::session::SessionState> state =
      keyframe->has_value() ? fd::session::SessionState::StartFromKeyframe(
                                  *settings, (*keyframe)->frame, (*keyframe)->basecolor)
                            : fd::session::SessionState::StartFromGBufferOnly(*settings);
  FD_FUZZ_CHECK(state.ok(), "a validated open starts a state");
  FD_FUZZ_CHECK(state->settings() == *settings, "state keeps the settings");
}

void Resume(const v1::ResumeSession& resume) {
  // What StreamController checks before it asks the store.
  if (resume.session_id().empty() || !fd::session::IsWellFormedToken(resume.session_id())) return;
  absl::StatusOr<std::unique_ptr<fd::session::SessionStore>> store =
      fd::session::SessionStore::Create({}, fd::session::RealClock::Get());
  FD_FUZZ_CHECK(store.ok(), "store");
  fd::session::SessionSettings settings;
  settings.environment = "street";
  settings.width = settings.height = 8;
  settings.steps = 1;
  absl::StatusOr<fd::session::SessionState> state =
      fd::session::SessionState::StartFromGBufferOnly(settings);
  FD_FUZZ_CHECK(state.ok(), "state");
  absl::StatusOr<fd::session::CreatedSession> created =
      (*store)->Create("client", *std::move(state), "0123456789abcdef0123456789abcdef");
  FD_FUZZ_CHECK(created.ok(), "create");
  absl::StatusOr<std::shared_ptr<fd::session::Session>> resumed =
      (*store)->Resume(resume.session_id(), resume.resume_token(), "client");
  if (resumed.ok()) {
    // Only the right secret for the one session resumes it.
    FD_FUZZ_CHECK(resume.resume_token() == created->resume_secret, "secret checked");
    return;
  }
  const absl::StatusCode code = resumed.status().code();
  FD_FUZZ_CHECK(
      code == absl::StatusCode::kNotFound || code == absl::StatusCode::kPermissionDenied ||
          code == absl::StatusCode::kUnauthenticated || code == absl::StatusCode::kInvalidArgument,
      "resume error code");
  FD_FUZZ_CHECK(resumed.status().message().size() <= fd::fuzz::kMaxErrorMessageBytes,
                "bounded message");
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  v1::RenderRequest request;
  if (!request.ParseFromArray(data, static_cast<int>(size))) return 0;
  if (request.has_open()) Open(request.open());
  if (request.has_resume()) Resume(request.resume());
  return 0;
}

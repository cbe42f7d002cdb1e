// OpenSession -> the settings a session runs with (the environment's
// defaults and the server's limits applied), and the wire forms of settings
// and environments.
#ifndef FD_SERVER_OPEN_SETTINGS_H_
#define FD_SERVER_OPEN_SETTINGS_H_

#include <cstdint>

#include "absl/status/statusor.h"
#include "framediffuser/v1/render_service.pb.h"
#include "session/environment_registry.h"
#include "session/session_settings.h"

namespace fd::server {

namespace v1 = ::framediffuser::v1;

// Server-wide limits on what a session may ask for (from ServerConfig).
struct SessionLimits {
  uint32_t min_size = 64;  // width/height in pixels, multiples of 8
  uint32_t max_size = 1024;
  uint32_t max_steps = 50;
  // Default and cap of OpenSession.max_frames_in_flight.
  uint32_t max_frames_in_flight = 2;
};

// Resolves `open` for environment `env`: zero fields take the environment's
// defaults (size, steps, scheduler, sky mode), seed 0 takes `random_seed`,
// max_frames_in_flight is capped silently (SessionOpened reports it).
// INVALID_ARGUMENT naming the field ("open.width: must be a multiple of 8 in
// [64, 1024], got 500", "open.steps: ...", "open.scheduler: ...", unknown
// enum values, a sampler the environment's scheduler config lacks).
// Thread-safety: pure function.
absl::StatusOr<session::SessionSettings> ResolveOpenSettings(const v1::OpenSession& open,
                                                             const session::EnvironmentInfo& env,
                                                             const SessionLimits& limits,
                                                             uint64_t random_seed);

// The wire form of a session's settings.
v1::SessionSettings ToWireSettings(const session::SessionSettings& settings,
                                   bool started_from_keyframe);

// The wire form of an environment (ListEnvironments).
v1::Environment ToWireEnvironment(const session::EnvironmentInfo& info,
                                  const SessionLimits& limits);

}  // namespace fd::server

#endif  // FD_SERVER_OPEN_SETTINGS_H_

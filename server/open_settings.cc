#include "server/open_settings.h"

#include <algorithm>
#include <string>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "server/wire_enums.h"

namespace fd::server {
namespace {

absl::Status CheckSize(const char* field, uint32_t value, const SessionLimits& limits) {
  if (value % 8 != 0 || value < limits.min_size || value > limits.max_size) {
    return absl::InvalidArgumentError(absl::StrCat(field, ": must be a multiple of 8 in [",
                                                   limits.min_size, ", ", limits.max_size,
                                                   "], got ", value));
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<session::SessionSettings> ResolveOpenSettings(const v1::OpenSession& open,
                                                             const session::EnvironmentInfo& env,
                                                             const SessionLimits& limits,
                                                             uint64_t random_seed) {
  session::SessionSettings settings;
  settings.environment = env.name;

  settings.width = open.width() == 0 ? env.native_width : open.width();
  settings.height = open.height() == 0 ? env.native_height : open.height();
  if (absl::Status s = CheckSize("open.width", settings.width, limits); !s.ok()) return s;
  if (absl::Status s = CheckSize("open.height", settings.height, limits); !s.ok()) return s;

  settings.seed = open.seed() != 0 ? open.seed() : (random_seed != 0 ? random_seed : 1);

  settings.steps = open.steps() == 0 ? env.default_steps : open.steps();
  if (settings.steps < 1 || settings.steps > limits.max_steps) {
    return absl::InvalidArgumentError(absl::StrCat("open.steps: must be in [1, ", limits.max_steps,
                                                   "] (0 = the default ", env.default_steps,
                                                   "), got ", open.steps()));
  }

  absl::StatusOr<std::optional<session::SchedulerKind>> scheduler =
      SchedulerFromWire(static_cast<int>(open.scheduler()), "open.scheduler");
  if (!scheduler.ok()) return scheduler.status();
  settings.scheduler = scheduler->value_or(env.default_scheduler);
  if (std::find(env.schedulers.begin(), env.schedulers.end(), settings.scheduler) ==
      env.schedulers.end()) {
    std::vector<std::string> names;
    for (session::SchedulerKind kind : env.schedulers) {
      names.emplace_back(session::SchedulerKindName(kind));
    }
    return absl::InvalidArgumentError(
        absl::StrCat("open.scheduler: environment '", env.name, "' has no ",
                     std::string(session::SchedulerKindName(settings.scheduler)),
                     " sampler (available: ", absl::StrJoin(names, ", "), ")"));
  }

  absl::StatusOr<std::optional<session::SkyMode>> sky =
      SkyModeFromWire(static_cast<int>(open.sky_mode()), "open.sky_mode");
  if (!sky.ok()) return sky.status();
  settings.sky_mode = sky->value_or(env.default_sky_mode);

  absl::StatusOr<std::optional<session::OutputDType>> dtype =
      OutputDTypeFromWire(static_cast<int>(open.output_dtype()), "open.output_dtype");
  if (!dtype.ok()) return dtype.status();
  settings.output_dtype = dtype->value_or(session::OutputDType::kUint8);

  absl::StatusOr<session::OutputCompression> compression = OutputCompressionFromWire(
      static_cast<int>(open.output_compression()), "open.output_compression");
  if (!compression.ok()) return compression.status();
  settings.output_compression = *compression;

  const uint32_t cap = std::max<uint32_t>(1, limits.max_frames_in_flight);
  settings.max_frames_in_flight =
      open.max_frames_in_flight() == 0 ? cap : std::min(open.max_frames_in_flight(), cap);

  if (absl::Status valid = session::ValidateSessionSettings(settings); !valid.ok()) {
    return absl::InvalidArgumentError(absl::StrCat("open: ", valid.message()));
  }
  return settings;
}

v1::SessionSettings ToWireSettings(const session::SessionSettings& settings,
                                   bool started_from_keyframe) {
  v1::SessionSettings wire;
  wire.set_environment(settings.environment);
  wire.set_width(settings.width);
  wire.set_height(settings.height);
  wire.set_seed(settings.seed);
  wire.set_steps(settings.steps);
  wire.set_scheduler(ToWire(settings.scheduler));
  wire.set_sky_mode(ToWire(settings.sky_mode));
  wire.set_output_dtype(ToWire(settings.output_dtype));
  wire.set_output_compression(ToWire(settings.output_compression));
  wire.set_max_frames_in_flight(settings.max_frames_in_flight);
  wire.set_started_from_keyframe(started_from_keyframe);
  return wire;
}

v1::Environment ToWireEnvironment(const session::EnvironmentInfo& info,
                                  const SessionLimits& limits) {
  v1::Environment wire;
  wire.set_name(info.name);
  wire.set_description(info.description);
  wire.set_prompt(info.prompt);
  wire.set_native_width(info.native_width);
  wire.set_native_height(info.native_height);
  wire.set_default_steps(info.default_steps);
  wire.set_max_steps(limits.max_steps);
  wire.set_default_scheduler(ToWire(info.default_scheduler));
  wire.set_default_sky_mode(ToWire(info.default_sky_mode));
  wire.set_readiness(ToWire(info.readiness));
  if (info.readiness != session::Readiness::kReady)
    wire.set_readiness_detail(info.readiness_detail);
  wire.set_min_size(limits.min_size);
  wire.set_max_size(limits.max_size);
  return wire;
}

}  // namespace fd::server

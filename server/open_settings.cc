#include "server/open_settings.h"

#include <algorithm>
#include <string>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

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
                                                             const EnvironmentInfo& env,
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

  const int scheduler = static_cast<int>(open.scheduler());
  if (scheduler == v1::SCHEDULER_UNSPECIFIED) {
    settings.scheduler = env.default_scheduler;
  } else if (scheduler < 0 || scheduler > 255 ||
             !session::IsValidSchedulerKind(static_cast<uint8_t>(scheduler))) {
    return absl::InvalidArgumentError(
        absl::StrCat("open.scheduler: unknown value ", scheduler));
  } else {
    settings.scheduler = static_cast<session::SchedulerKind>(scheduler);
  }
  if (std::find(env.schedulers.begin(), env.schedulers.end(), settings.scheduler) ==
      env.schedulers.end()) {
    std::vector<std::string> names;
    for (session::SchedulerKind kind : env.schedulers) {
      names.emplace_back(session::SchedulerKindName(kind));
    }
    return absl::InvalidArgumentError(absl::StrCat(
        "open.scheduler: environment '", env.name, "' has no ",
        std::string(session::SchedulerKindName(settings.scheduler)),
        " sampler (available: ", absl::StrJoin(names, ", "), ")"));
  }

  const int sky = static_cast<int>(open.sky_mode());
  if (sky == v1::SKY_MODE_UNSPECIFIED) {
    settings.sky_mode = env.default_sky_mode;
  } else if (sky < 0 || sky > 255 || !session::IsValidSkyMode(static_cast<uint8_t>(sky))) {
    return absl::InvalidArgumentError(absl::StrCat("open.sky_mode: unknown value ", sky));
  } else {
    settings.sky_mode = static_cast<session::SkyMode>(sky);
  }

  const int dtype = static_cast<int>(open.output_dtype());
  if (dtype == v1::DTYPE_UNSPECIFIED) {
    settings.output_dtype = session::OutputDType::kUint8;
  } else if (dtype < 0 || dtype > 255 || !session::IsValidOutputDType(static_cast<uint8_t>(dtype))) {
    return absl::InvalidArgumentError(absl::StrCat("open.output_dtype: unknown value ", dtype));
  } else {
    settings.output_dtype = static_cast<session::OutputDType>(dtype);
  }

  const int compression = static_cast<int>(open.output_compression());
  if (compression < 0 || compression > 255 ||
      !session::IsValidOutputCompression(static_cast<uint8_t>(compression))) {
    return absl::InvalidArgumentError(
        absl::StrCat("open.output_compression: unknown value ", compression));
  }
  settings.output_compression = static_cast<session::OutputCompression>(compression);

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
  wire.set_scheduler(static_cast<v1::Scheduler>(settings.scheduler));
  wire.set_sky_mode(static_cast<v1::SkyMode>(settings.sky_mode));
  wire.set_output_dtype(static_cast<v1::DType>(settings.output_dtype));
  wire.set_output_compression(static_cast<v1::Compression>(settings.output_compression));
  wire.set_max_frames_in_flight(settings.max_frames_in_flight);
  wire.set_started_from_keyframe(started_from_keyframe);
  return wire;
}

v1::Environment ToWireEnvironment(const EnvironmentInfo& info, const SessionLimits& limits) {
  v1::Environment wire;
  wire.set_name(info.name);
  wire.set_description(info.description);
  wire.set_prompt(info.prompt);
  wire.set_native_width(info.native_width);
  wire.set_native_height(info.native_height);
  wire.set_default_steps(info.default_steps);
  wire.set_max_steps(limits.max_steps);
  wire.set_default_scheduler(static_cast<v1::Scheduler>(info.default_scheduler));
  wire.set_default_sky_mode(static_cast<v1::SkyMode>(info.default_sky_mode));
  wire.set_readiness(static_cast<v1::Readiness>(info.readiness));
  if (info.readiness != Readiness::kReady) wire.set_readiness_detail(info.readiness_detail);
  wire.set_min_size(limits.min_size);
  wire.set_max_size(limits.max_size);
  return wire;
}

}  // namespace fd::server

#include "session/session_settings.h"

#include "absl/strings/str_cat.h"

namespace fd::session {

bool IsValidSchedulerKind(uint8_t value) { return value >= 1 && value <= 4; }
bool IsValidSkyMode(uint8_t value) { return value >= 1 && value <= 3; }
bool IsValidOutputDType(uint8_t value) { return value >= 1 && value <= 3; }
bool IsValidOutputCompression(uint8_t value) { return value <= 1; }
bool IsValidStartMode(uint8_t value) { return value >= 1 && value <= 2; }

std::string_view SchedulerKindName(SchedulerKind kind) {
  switch (kind) {
    case SchedulerKind::kUniPC:
      return "unipc";
    case SchedulerKind::kDpmSolverPP2M:
      return "dpm_solver_pp_2m";
    case SchedulerKind::kDDIM:
      return "ddim";
    case SchedulerKind::kEulerDiscrete:
      return "euler";
  }
  return "invalid";
}

std::string_view SkyModeName(SkyMode mode) {
  switch (mode) {
    case SkyMode::kClientImage:
      return "client_image";
    case SkyMode::kPreviousOutput:
      return "previous_output";
    case SkyMode::kOff:
      return "off";
  }
  return "invalid";
}

std::string_view OutputDTypeName(OutputDType dtype) {
  switch (dtype) {
    case OutputDType::kUint8:
      return "uint8";
    case OutputDType::kFloat16:
      return "float16";
    case OutputDType::kFloat32:
      return "float32";
  }
  return "invalid";
}

std::string_view OutputCompressionName(OutputCompression compression) {
  switch (compression) {
    case OutputCompression::kNone:
      return "none";
    case OutputCompression::kZstd:
      return "zstd";
  }
  return "invalid";
}

std::string_view StartModeName(StartMode mode) {
  switch (mode) {
    case StartMode::kKeyframe:
      return "keyframe";
    case StartMode::kGBufferOnly:
      return "gbuffer_only";
  }
  return "invalid";
}

bool operator==(const SessionSettings& a, const SessionSettings& b) {
  return a.environment == b.environment && a.width == b.width && a.height == b.height &&
         a.seed == b.seed && a.steps == b.steps && a.scheduler == b.scheduler &&
         a.sky_mode == b.sky_mode && a.output_dtype == b.output_dtype &&
         a.output_compression == b.output_compression &&
         a.max_frames_in_flight == b.max_frames_in_flight;
}

absl::Status ValidateSessionSettings(const SessionSettings& s) {
  if (s.environment.empty()) {
    return absl::InvalidArgumentError("settings.environment: must not be empty");
  }
  if (s.width < 1 || s.width > kMaxImageSide) {
    return absl::InvalidArgumentError(
        absl::StrCat("settings.width: must be in [1, ", kMaxImageSide, "], got ", s.width));
  }
  if (s.height < 1 || s.height > kMaxImageSide) {
    return absl::InvalidArgumentError(
        absl::StrCat("settings.height: must be in [1, ", kMaxImageSide, "], got ", s.height));
  }
  if (s.steps < 1) {
    return absl::InvalidArgumentError("settings.steps: must be at least 1, got 0");
  }
  if (s.max_frames_in_flight < 1) {
    return absl::InvalidArgumentError("settings.max_frames_in_flight: must be at least 1, got 0");
  }
  if (!IsValidSchedulerKind(static_cast<uint8_t>(s.scheduler))) {
    return absl::InvalidArgumentError(
        absl::StrCat("settings.scheduler: invalid value ", static_cast<int>(s.scheduler)));
  }
  if (!IsValidSkyMode(static_cast<uint8_t>(s.sky_mode))) {
    return absl::InvalidArgumentError(
        absl::StrCat("settings.sky_mode: invalid value ", static_cast<int>(s.sky_mode)));
  }
  if (!IsValidOutputDType(static_cast<uint8_t>(s.output_dtype))) {
    return absl::InvalidArgumentError(
        absl::StrCat("settings.output_dtype: invalid value ", static_cast<int>(s.output_dtype)));
  }
  if (!IsValidOutputCompression(static_cast<uint8_t>(s.output_compression))) {
    return absl::InvalidArgumentError(absl::StrCat("settings.output_compression: invalid value ",
                                                   static_cast<int>(s.output_compression)));
  }
  return absl::OkStatus();
}

}  // namespace fd::session

#include "server/wire_enums.h"

#include <cstdint>

#include "absl/strings/str_cat.h"

namespace fd::server {
namespace {

// The values are meant to match; a change on either side fails here.
static_assert(static_cast<int>(session::SchedulerKind::kUniPC) == v1::SCHEDULER_UNIPC);
static_assert(static_cast<int>(session::SchedulerKind::kDpmSolverPP2M) ==
              v1::SCHEDULER_DPM_SOLVER_PP_2M);
static_assert(static_cast<int>(session::SchedulerKind::kDDIM) == v1::SCHEDULER_DDIM);
static_assert(static_cast<int>(session::SchedulerKind::kEulerDiscrete) == v1::SCHEDULER_EULER);
static_assert(static_cast<int>(session::SkyMode::kClientImage) == v1::SKY_MODE_CLIENT_IMAGE);
static_assert(static_cast<int>(session::SkyMode::kPreviousOutput) == v1::SKY_MODE_PREVIOUS_OUTPUT);
static_assert(static_cast<int>(session::SkyMode::kOff) == v1::SKY_MODE_OFF);
static_assert(static_cast<int>(session::OutputDType::kUint8) == v1::DTYPE_UINT8);
static_assert(static_cast<int>(session::OutputDType::kFloat16) == v1::DTYPE_FLOAT16);
static_assert(static_cast<int>(session::OutputDType::kFloat32) == v1::DTYPE_FLOAT32);
static_assert(static_cast<int>(session::OutputCompression::kNone) == v1::COMPRESSION_NONE);
static_assert(static_cast<int>(session::OutputCompression::kZstd) == v1::COMPRESSION_ZSTD);
static_assert(static_cast<int>(session::Readiness::kLoading) == v1::READINESS_LOADING);
static_assert(static_cast<int>(session::Readiness::kReady) == v1::READINESS_READY);
static_assert(static_cast<int>(session::Readiness::kFailed) == v1::READINESS_FAILED);
static_assert(static_cast<int>(session::Readiness::kUnloading) == v1::READINESS_UNLOADING);
static_assert(static_cast<int>(session::EndReason::kDraining) ==
              v1::SessionNotice::REASON_DRAINING);
static_assert(static_cast<int>(session::EndReason::kEvicted) == v1::SessionNotice::REASON_EVICTED);
static_assert(static_cast<int>(session::EndReason::kExpired) == v1::SessionNotice::REASON_EXPIRED);
static_assert(static_cast<int>(session::EndReason::kClosed) == v1::SessionNotice::REASON_CLOSED);

// `value` as the session enum when `valid` accepts it; 0 is "unspecified"
// (nullopt) unless `zero_is_value`.
template <typename Enum>
absl::StatusOr<std::optional<Enum>> FromWire(int value, bool (*valid)(uint8_t), bool zero_is_value,
                                             std::string_view field) {
  if (value == 0 && !zero_is_value) return std::nullopt;
  if (value < 0 || value > 255 || !valid(static_cast<uint8_t>(value))) {
    return absl::InvalidArgumentError(
        absl::StrCat(absl::string_view(field.data(), field.size()), ": unknown value ", value));
  }
  return static_cast<Enum>(value);
}

}  // namespace

absl::StatusOr<std::optional<session::SchedulerKind>> SchedulerFromWire(int value,
                                                                        std::string_view field) {
  return FromWire<session::SchedulerKind>(value, &session::IsValidSchedulerKind, false, field);
}
absl::StatusOr<std::optional<session::SkyMode>> SkyModeFromWire(int value, std::string_view field) {
  return FromWire<session::SkyMode>(value, &session::IsValidSkyMode, false, field);
}
absl::StatusOr<std::optional<session::OutputDType>> OutputDTypeFromWire(int value,
                                                                        std::string_view field) {
  return FromWire<session::OutputDType>(value, &session::IsValidOutputDType, false, field);
}
absl::StatusOr<session::OutputCompression> OutputCompressionFromWire(int value,
                                                                     std::string_view field) {
  absl::StatusOr<std::optional<session::OutputCompression>> parsed =
      FromWire<session::OutputCompression>(value, &session::IsValidOutputCompression, true, field);
  if (!parsed.ok()) return parsed.status();
  return **parsed;
}

v1::Scheduler ToWire(session::SchedulerKind kind) { return static_cast<v1::Scheduler>(kind); }
v1::SkyMode ToWire(session::SkyMode mode) { return static_cast<v1::SkyMode>(mode); }
v1::DType ToWire(session::OutputDType dtype) { return static_cast<v1::DType>(dtype); }
v1::Compression ToWire(session::OutputCompression compression) {
  return static_cast<v1::Compression>(compression);
}
v1::Readiness ToWire(session::Readiness readiness) { return static_cast<v1::Readiness>(readiness); }
v1::SessionNotice::Reason ToWire(session::EndReason reason) {
  return static_cast<v1::SessionNotice::Reason>(reason);
}

}  // namespace fd::server

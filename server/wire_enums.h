// The one place where the wire enums (framediffuser.v1) and the session's
// enums (session/session_settings.h, end_reason.h, environment_registry.h)
// meet. Their values are equal by design, checked by static_asserts in
// wire_enums.cc, so the conversions are casts after a range check.
// Thread-safety: pure functions.
#ifndef FD_SERVER_WIRE_ENUMS_H_
#define FD_SERVER_WIRE_ENUMS_H_

#include <optional>
#include <string_view>

#include "absl/status/statusor.h"
#include "framediffuser/v1/image.pb.h"
#include "framediffuser/v1/render_service.pb.h"
#include "session/end_reason.h"
#include "session/environment_registry.h"
#include "session/session_settings.h"

namespace fd::server {

namespace v1 = ::framediffuser::v1;

// Wire -> session. nullopt for UNSPECIFIED (0: the caller applies its
// default); INVALID_ARGUMENT "<field>: unknown value N" for a value the
// session does not know.
absl::StatusOr<std::optional<session::SchedulerKind>> SchedulerFromWire(int value,
                                                                        std::string_view field);
absl::StatusOr<std::optional<session::SkyMode>> SkyModeFromWire(int value, std::string_view field);
absl::StatusOr<std::optional<session::OutputDType>> OutputDTypeFromWire(int value,
                                                                        std::string_view field);
// COMPRESSION_NONE is 0 on the wire and a real value, never "unspecified".
absl::StatusOr<session::OutputCompression> OutputCompressionFromWire(int value,
                                                                     std::string_view field);

// Session -> wire.
v1::Scheduler ToWire(session::SchedulerKind kind);
v1::SkyMode ToWire(session::SkyMode mode);
v1::DType ToWire(session::OutputDType dtype);
v1::Compression ToWire(session::OutputCompression compression);
v1::Readiness ToWire(session::Readiness readiness);
v1::SessionNotice::Reason ToWire(session::EndReason reason);

}  // namespace fd::server

#endif  // FD_SERVER_WIRE_ENUMS_H_

// The settings a session runs with, after the server applied the
// environment's defaults (the wire API's SessionSettings, as plain C++).
//
// The enum values equal the wire API's (framediffuser.v1 Scheduler, SkyMode,
// DType, Compression) so the server maps them with a cast after checking
// IsValid*(); session/ itself does not depend on the generated code. There is
// no "unspecified" value: defaults are resolved before a session exists.
#ifndef FD_SESSION_SESSION_SETTINGS_H_
#define FD_SESSION_SESSION_SETTINGS_H_

#include <cstdint>
#include <string>
#include <string_view>

#include "absl/status/status.h"

namespace fd::session {

// The denoising sampler of every frame.
enum class SchedulerKind : uint8_t {
  kUniPC = 1,          // UniPC multistep, bh2 (the authors' inference sampler)
  kDpmSolverPP2M = 2,  // DPM-Solver++ 2M, midpoint (the paper's sampler)
  kDDIM = 3,           // DDIM, eta 0
  kEulerDiscrete = 4,  // Euler discrete
};

// Where sky pixels take their basecolor from before conditioning.
enum class SkyMode : uint8_t {
  kClientImage = 1,     // FrameInput.sky, sent with every frame
  kPreviousOutput = 2,  // the session's previous output frame
  kOff = 3,             // left black
};

// Element type of the rendered frames sent to the client.
enum class OutputDType : uint8_t {
  kUint8 = 1,
  kFloat16 = 2,
  kFloat32 = 3,
};

// Compression of the rendered frames sent to the client.
enum class OutputCompression : uint8_t {
  kNone = 0,
  kZstd = 1,
};

// How the session's autoregressive chain started.
enum class StartMode : uint8_t {
  // From a client keyframe: the first frame is conditioned on it.
  kKeyframe = 1,
  // From the G-buffer only: black irradiance and a zero previous latent until
  // the first output exists (takes a few frames to converge).
  kGBufferOnly = 2,
};

bool IsValidSchedulerKind(uint8_t value);
bool IsValidSkyMode(uint8_t value);
bool IsValidOutputDType(uint8_t value);
bool IsValidOutputCompression(uint8_t value);
bool IsValidStartMode(uint8_t value);

// Lowercase names for messages and logs, e.g. "unipc", "previous_output".
std::string_view SchedulerKindName(SchedulerKind kind);
std::string_view SkyModeName(SkyMode mode);
std::string_view OutputDTypeName(OutputDType dtype);
std::string_view OutputCompressionName(OutputCompression compression);
std::string_view StartModeName(StartMode mode);

// Largest width or height a session may have. It bounds what an imported
// state blob may make us allocate (a blob names its own size).
inline constexpr uint32_t kMaxImageSide = 4096;

// Value type; copyable. Thread-safety: none (a plain struct).
struct SessionSettings {
  std::string environment;  // environment name, e.g. "downtown_west"
  uint32_t width = 0;       // frame size in pixels
  uint32_t height = 0;
  uint64_t seed = 0;   // session seed; frame k's noise uses FrameSeed(seed, k)
  uint32_t steps = 0;  // denoising steps per frame
  SchedulerKind scheduler = SchedulerKind::kUniPC;
  SkyMode sky_mode = SkyMode::kOff;
  OutputDType output_dtype = OutputDType::kUint8;
  OutputCompression output_compression = OutputCompression::kNone;
  uint32_t max_frames_in_flight = 1;  // server-side flow control (read-ahead)

  friend bool operator==(const SessionSettings& a, const SessionSettings& b);
  friend bool operator!=(const SessionSettings& a, const SessionSettings& b) { return !(a == b); }
};

// Structural checks only (the environment's own limits are the server's):
// non-empty environment name, 1 <= width/height <= kMaxImageSide, steps >= 1,
// max_frames_in_flight >= 1, enum values in range. INVALID_ARGUMENT naming the
// field ("settings.width: ...") otherwise.
absl::Status ValidateSessionSettings(const SessionSettings& settings);

}  // namespace fd::session

#endif  // FD_SESSION_SESSION_SETTINGS_H_

// Small builders shared by the session tests.
#ifndef FD_TESTS_SESSION_SESSION_TEST_UTIL_H_
#define FD_TESTS_SESSION_SESSION_TEST_UTIL_H_

#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "session/session_settings.h"
#include "session/session_state.h"

namespace fd::session::testing {

inline SessionSettings MakeSettings(std::string environment = "downtown_west", uint32_t width = 64,
                                    uint32_t height = 32, uint64_t seed = 42) {
  SessionSettings s;
  s.environment = std::move(environment);
  s.width = width;
  s.height = height;
  s.seed = seed;
  s.steps = 10;
  s.scheduler = SchedulerKind::kUniPC;
  s.sky_mode = SkyMode::kPreviousOutput;
  s.output_dtype = OutputDType::kFloat16;
  s.output_compression = OutputCompression::kZstd;
  s.max_frames_in_flight = 2;
  return s;
}

// A deterministic, not very compressible uint8 RGB image (an LCG per pixel
// byte, mixed with a gradient so zstd has something to do).
inline std::vector<uint8_t> MakeImage(const SessionSettings& s, uint32_t salt) {
  std::vector<uint8_t> pixels(static_cast<size_t>(s.width) * s.height * 3);
  uint32_t x = 2654435761u * (salt + 1);
  for (size_t i = 0; i < pixels.size(); ++i) {
    x = x * 1664525u + 1013904223u;
    pixels[i] = static_cast<uint8_t>(((x >> 24) & 0x0f) + (i * 7 / pixels.size()) * 32);
  }
  return pixels;
}

inline SessionState MakeGBufferOnlyState(SessionSettings s = MakeSettings()) {
  return *SessionState::StartFromGBufferOnly(std::move(s));
}

}  // namespace fd::session::testing

#endif  // FD_TESTS_SESSION_SESSION_TEST_UTIL_H_

// Small builders shared by the session tests.
#ifndef FD_TESTS_SESSION_SESSION_TEST_UTIL_H_
#define FD_TESTS_SESSION_SESSION_TEST_UTIL_H_

#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "base/image_buffer.h"
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
inline ImageBuffer MakeImage(const SessionSettings& s, uint32_t salt) {
  ImageBuffer image(s.width, s.height, 3, PixelType::kUint8);
  uint8_t* pixels = image.mutable_data();
  const size_t n = image.size_bytes();
  uint32_t x = 2654435761u * (salt + 1);
  for (size_t i = 0; i < n; ++i) {
    x = x * 1664525u + 1013904223u;
    pixels[i] = static_cast<uint8_t>(((x >> 24) & 0x0f) + (i * 7 / n) * 32);
  }
  return image;
}

inline SessionState MakeGBufferOnlyState(SessionSettings s = MakeSettings()) {
  return *SessionState::StartFromGBufferOnly(std::move(s));
}

}  // namespace fd::session::testing

#endif  // FD_TESTS_SESSION_SESSION_TEST_UTIL_H_

// A random-weight environment for tests and benchmarks: the tiny preset
// (model/presets/presets.h: the real architecture — UNet with the 8-channel conv_in
// and ControlLoRA, the 10-channel ControlNet, the VAE — at toy widths) with
// weights drawn from a fixed seed, so every build makes the same model and
// renders the same frames for the same inputs. Its frames are deterministic,
// structured noise; its environment.json says so. The server never serves it
// on its own (the embedded default is the trained street environment,
// server/embedded_environment.h).
#ifndef FD_SESSION_RANDOM_ENVIRONMENT_H_
#define FD_SESSION_RANDOM_ENVIRONMENT_H_

#include <cstdint>
#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "model/pipeline/environment.h"

namespace fd::session {

inline constexpr uint64_t kRandomEnvironmentSeed = 20261122;
inline constexpr int kRandomEnvironmentSize = 128;  // native width and height
inline constexpr int kRandomEnvironmentSteps = 10;  // the authors' default

// Writes the random environment's checkpoint folder (+ environment.json)
// into `dir` (created; existing files replaced). INTERNAL on I/O errors.
// Thread-safe for distinct dirs. Another `seed` draws other weights (same
// architecture and settings; the description names the seed), so a test can
// tell two versions of one environment apart by what they render.
absl::Status WriteRandomTinyEnvironment(const std::string& dir,
                                        uint64_t seed = kRandomEnvironmentSeed);

// Writes it into a fresh folder under `scratch_root` (the system temporary
// folder when empty), loads it with `options`, and removes the folder again.
// Errors from writing or LoadEnvironment. Takes well under a second.
absl::StatusOr<std::shared_ptr<model::Environment>> CreateRandomTinyEnvironment(
    const model::EnvironmentOptions& options, const std::string& scratch_root = "");

}  // namespace fd::session

#endif  // FD_SESSION_RANDOM_ENVIRONMENT_H_

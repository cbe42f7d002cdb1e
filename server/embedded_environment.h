// The built-in environment a server serves when no model repository is
// given, so that the README demo works with zero set-up.
//
// It is NOT a trained model: a tiny FrameDiffuser (model/presets.h
// preset "tiny": the real architecture — UNet with the 8-channel conv_in and
// ControlLoRA, the 10-channel ControlNet, the VAE — at toy widths) with
// RANDOM weights drawn from a fixed seed, so every server builds the same
// model and renders the same frames for the same inputs. Its frames are
// deterministic, structured noise, not a lit scene. ListEnvironments says so
// in its description.
#ifndef FD_SERVER_EMBEDDED_ENVIRONMENT_H_
#define FD_SERVER_EMBEDDED_ENVIRONMENT_H_

#include <cstdint>
#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "model/environment.h"

namespace fd::server {

inline constexpr char kEmbeddedEnvironmentName[] = "default";
inline constexpr uint64_t kEmbeddedEnvironmentSeed = 20261122;
inline constexpr int kEmbeddedEnvironmentSize = 128;  // native width and height
inline constexpr int kEmbeddedEnvironmentSteps = 10;  // the authors' default

// Writes the embedded environment's checkpoint folder (+ environment.json)
// into `dir` (created; existing files replaced). INTERNAL on I/O errors.
absl::Status WriteEmbeddedEnvironment(const std::string& dir);

// Writes it into a fresh folder under `scratch_root` (the system temporary
// folder when empty), loads it with `options`, and removes the folder again.
// Errors from writing or LoadEnvironment. Takes well under a second.
absl::StatusOr<std::shared_ptr<model::Environment>> CreateEmbeddedEnvironment(
    const model::EnvironmentOptions& options, const std::string& scratch_root = "");

}  // namespace fd::server

#endif  // FD_SERVER_EMBEDDED_ENVIRONMENT_H_

// The environment a server serves when no model repository is given: the
// trained `street` environment of environments/street/ (fp16 safetensors in
// the authors' checkpoint layout, trained by framediffuser-train; its
// environment.json records the data, command, seed, steps and time), compiled
// into the binary (cmake/FdEmbedFiles.cmake), so a fresh clone's demo renders
// lit frames and no file outside the binary is needed.
#ifndef FD_SERVER_EMBEDDED_ENVIRONMENT_H_
#define FD_SERVER_EMBEDDED_ENVIRONMENT_H_

#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "model/environment.h"
#include "server/embedded_file.h"

namespace fd::server {

inline constexpr char kEmbeddedEnvironmentName[] = "default";

// The embedded files (paths relative to the environment folder).
std::vector<embedded::File> EmbeddedEnvironmentFiles();

// Writes the embedded environment folder into `dir` (created; existing
// files replaced). INTERNAL on I/O errors. Thread-safe for distinct dirs.
absl::Status WriteEmbeddedEnvironment(const std::string& dir);

// Writes it into a fresh folder under `scratch_root` (the system temporary
// folder when empty), loads it with `options` (strict key checks, the
// ControlLoRA required), and removes the folder again. Errors from writing or
// LoadEnvironment.
absl::StatusOr<std::shared_ptr<model::Environment>> CreateEmbeddedEnvironment(
    const model::EnvironmentOptions& options, const std::string& scratch_root = "");

}  // namespace fd::server

#endif  // FD_SERVER_EMBEDDED_ENVIRONMENT_H_

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
#include "server/embedded_file.h"
#include "session/environment_registry.h"

namespace fd::server {

inline constexpr char kEmbeddedEnvironmentName[] = "default";

// The embedded files (paths relative to the environment folder).
std::vector<embedded::File> EmbeddedEnvironmentFiles();

// The folder name the embedded files are served under (in messages, e.g.
// "<embedded>/default/unet/config.json").
inline constexpr char kEmbeddedEnvironmentRoot[] = "<embedded>/default";

// Loads the embedded environment straight from the binary's bytes (no
// temporary files) with `options` (strict key checks, the ControlLoRA
// required; options.files is replaced). Errors from LoadEnvironment.
absl::StatusOr<std::shared_ptr<session::EnvironmentModel>> CreateEmbeddedEnvironment(
    const session::EnvironmentLoadOptions& options);

}  // namespace fd::server

#endif  // FD_SERVER_EMBEDDED_ENVIRONMENT_H_

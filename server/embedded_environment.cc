#include "server/embedded_environment.h"

#include <stdlib.h>

#include <filesystem>
#include <fstream>
#include <string>
#include <system_error>

#include "absl/strings/str_cat.h"
#include "model/presets.h"
#include "nlohmann/json.hpp"

namespace fd::server {
namespace {

namespace fs = std::filesystem;

std::string EnvironmentJson() {
  nlohmann::json json = {
      {"name", kEmbeddedEnvironmentName},
      {"description",
       absl::StrCat("Built-in demo environment: a tiny FrameDiffuser (the real architecture at toy "
                    "widths) with RANDOMLY INITIALISED weights (seed ",
                    kEmbeddedEnvironmentSeed,
                    "). Its frames are deterministic noise-like images, not a trained render; "
                    "start the server with --model_repository for real models.")},
      {"prompt", "a photorealistic street at daytime"},
      {"width", kEmbeddedEnvironmentSize},
      {"height", kEmbeddedEnvironmentSize},
      {"steps", kEmbeddedEnvironmentSteps},
      {"scheduler", "unipc"},
      // The demo client sends no sky image: fill sky pixels from the
      // previous output instead.
      {"sky_mode", "previous_output"},
  };
  return json.dump(2) + "\n";
}

}  // namespace

absl::Status WriteEmbeddedEnvironment(const std::string& dir) {
  model::MakeCheckpointOptions options;
  options.preset = "tiny";
  options.out_dir = dir;
  options.seed = kEmbeddedEnvironmentSeed;
  if (absl::Status made = model::MakeCheckpoint(options); !made.ok()) return made;
  std::ofstream out(fs::path(dir) / "environment.json", std::ios::binary | std::ios::trunc);
  out << EnvironmentJson();
  out.close();
  if (!out) {
    return absl::InternalError(absl::StrCat("cannot write ", dir, "/environment.json"));
  }
  return absl::OkStatus();
}

absl::StatusOr<std::shared_ptr<model::Environment>> CreateEmbeddedEnvironment(
    const model::EnvironmentOptions& options, const std::string& scratch_root) {
  std::error_code ec;
  const fs::path root = scratch_root.empty() ? fs::temp_directory_path(ec) : fs::path(scratch_root);
  if (ec) return absl::InternalError(absl::StrCat("no temporary folder: ", ec.message()));
  std::string pattern = (root / "framediffuser-default-XXXXXX").string();
  if (mkdtemp(pattern.data()) == nullptr) {
    return absl::InternalError(absl::StrCat("cannot create a folder like ", pattern));
  }
  const std::string dir = pattern;
  absl::StatusOr<std::shared_ptr<model::Environment>> loaded;
  absl::Status written = WriteEmbeddedEnvironment(dir);
  if (written.ok()) {
    loaded = model::LoadEnvironment(dir, options);
  } else {
    loaded = written;
  }
  fs::remove_all(dir, ec);  // the loaded tensors do not refer to the files
  return loaded;
}

}  // namespace fd::server

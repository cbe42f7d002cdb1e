#include "session/random_environment.h"

#include <filesystem>
#include <fstream>
#include <string>

#include "absl/strings/str_cat.h"
#include "base/scratch_dir.h"
#include "model/presets/presets.h"
#include "nlohmann/json.hpp"

namespace fd::session {
namespace {

std::string EnvironmentJson(uint64_t seed) {
  nlohmann::json json = {
      {"name", "random-tiny"},
      {"description",
       absl::StrCat("Test environment: a tiny FrameDiffuser (the real architecture at toy "
                    "widths) with RANDOMLY INITIALISED weights (seed ",
                    seed,
                    "). Its frames are deterministic noise-like images, not a trained render.")},
      {"prompt", "a photorealistic street at daytime"},
      {"width", kRandomEnvironmentSize},
      {"height", kRandomEnvironmentSize},
      {"steps", kRandomEnvironmentSteps},
      {"scheduler", "unipc"},
      // Test clients send no sky image: fill sky pixels from the previous
      // output instead.
      {"sky_mode", "previous_output"},
  };
  return json.dump(2) + "\n";
}

}  // namespace

absl::Status WriteRandomTinyEnvironment(const std::string& dir, uint64_t seed) {
  model::MakeCheckpointOptions options;
  options.preset = "tiny";
  options.out_dir = dir;
  options.seed = seed;
  if (absl::Status made = model::MakeCheckpoint(options); !made.ok()) return made;
  std::ofstream out(std::filesystem::path(dir) / "environment.json",
                    std::ios::binary | std::ios::trunc);
  out << EnvironmentJson(seed);
  out.close();
  if (!out) {
    return absl::InternalError(absl::StrCat("cannot write ", dir, "/environment.json"));
  }
  return absl::OkStatus();
}

absl::StatusOr<std::shared_ptr<model::Environment>> CreateRandomTinyEnvironment(
    const model::EnvironmentOptions& options, const std::string& scratch_root) {
  absl::StatusOr<ScratchDir> dir = ScratchDir::Create(scratch_root, "framediffuser-random-");
  if (!dir.ok()) return dir.status();
  if (absl::Status written = WriteRandomTinyEnvironment(dir->path()); !written.ok()) {
    return written;
  }
  return model::LoadEnvironment(dir->path(), options);  // the tensors do not refer to the files
}

}  // namespace fd::session

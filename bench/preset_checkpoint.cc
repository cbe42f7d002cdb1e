#include "bench/preset_checkpoint.h"

#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <map>
#include <system_error>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "model/presets/presets.h"

namespace fd::bench {

absl::StatusOr<std::string> PresetCheckpointDir(const std::string& preset) {
  static auto* dirs = new std::map<std::string, std::string>;
  if (auto it = dirs->find(preset); it != dirs->end()) return it->second;
  const std::string dir = (std::filesystem::temp_directory_path() /
                           ("fd_bench_" + preset + "_" + std::to_string(getpid())))
                              .string();
  static const bool cleanup_registered = [] {
    std::atexit([] {
      for (const auto& [name, path] : *dirs) {
        std::error_code ignored;
        std::filesystem::remove_all(path, ignored);
      }
    });
    return true;
  }();
  (void)cleanup_registered;
  fd::model::MakeCheckpointOptions make;
  make.preset = preset;
  make.out_dir = dir;
  if (absl::Status made = fd::model::MakeCheckpoint(make); !made.ok()) {
    std::error_code ignored;
    std::filesystem::remove_all(dir, ignored);  // a half-written folder
    return absl::Status(made.code(),
                        absl::StrCat("cannot make the ", preset, " checkpoint: ", made.message()));
  }
  (*dirs)[preset] = dir;
  return dir;
}

}  // namespace fd::bench

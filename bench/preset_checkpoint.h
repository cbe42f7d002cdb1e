// Random-weight checkpoints of model/presets/presets.h's presets for the
// benchmarks (tiny, small, sd15): made once per preset into a temporary
// folder (float32 weights, seed 0) and removed when the process exits.
#ifndef FD_BENCH_PRESET_CHECKPOINT_H_
#define FD_BENCH_PRESET_CHECKPOINT_H_

#include <string>

#include "absl/status/statusor.h"

namespace fd::bench {

// The folder holding `preset`'s checkpoint (an environment folder that
// model::LoadEnvironment reads). Errors: INVALID_ARGUMENT for an unknown
// preset, or the maker's error for a failed write, with the preset named.
// Thread-safety: not thread-safe; call from main before threads start.
absl::StatusOr<std::string> PresetCheckpointDir(const std::string& preset);

}  // namespace fd::bench

#endif  // FD_BENCH_PRESET_CHECKPOINT_H_

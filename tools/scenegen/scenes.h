// Scene presets. Each preset is a function of a seed: the seed varies object
// placement, sizes and colours, while the camera path stays the same.
#ifndef FD_TOOLS_SCENEGEN_SCENES_H_
#define FD_TOOLS_SCENEGEN_SCENES_H_

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "tools/scenegen/scene.h"

namespace fd::scenegen {

struct SceneInfo {
  std::string name;
  std::string description;
};

// All presets, in a stable order.
const std::vector<SceneInfo>& SceneCatalog();

// Builds preset `name`, BVH and irradiance volume included, on `threads`
// threads (0 = all cores). INVALID_ARGUMENT naming the known presets when
// `name` is unknown. Deterministic in (name, seed); `threads` only changes
// how fast.
absl::StatusOr<Scene> MakeScene(const std::string& name, uint64_t seed, int threads = 0);

// Like MakeScene, but built once per process for each (name, seed): the
// most recently used few stay cached, since building the irradiance volume
// takes a good fraction of a second. The scene is immutable and safe to
// share between threads. Thread-safe.
absl::StatusOr<std::shared_ptr<const Scene>> SharedScene(const std::string& name, uint64_t seed,
                                                         int threads = 0);

// The presets themselves (scenes_street.cc, scenes_room.cc).
Scene BuildStreetScene(uint64_t seed, int threads = 0);
Scene BuildRoomScene(uint64_t seed, int threads = 0);

}  // namespace fd::scenegen

#endif  // FD_TOOLS_SCENEGEN_SCENES_H_

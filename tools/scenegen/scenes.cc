#include "tools/scenegen/scenes.h"

#include <list>
#include <mutex>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

namespace fd::scenegen {

const std::vector<SceneInfo>& SceneCatalog() {
  static const std::vector<SceneInfo>* const kCatalog = new std::vector<SceneInfo>{
      {"street",
       "outdoor street: road crossing, sidewalks, brick and glass building blocks, trees, lamp "
       "posts, parked cars, metal spheres, open sky; the camera walks, turns and flies up"},
      {"room",
       "indoor room lit by the sun through windows and a door, with a dark windowless back "
       "room (like the paper's Hillside case); the camera walks into the dark room and back"},
  };
  return *kCatalog;
}

absl::StatusOr<Scene> MakeScene(const std::string& name, uint64_t seed, int threads) {
  if (name == "street") return BuildStreetScene(seed, threads);
  if (name == "room") return BuildRoomScene(seed, threads);
  std::vector<std::string> names;
  for (const SceneInfo& info : SceneCatalog()) names.push_back(info.name);
  return absl::InvalidArgumentError(
      absl::StrCat("unknown scene '", name, "' (known: ", absl::StrJoin(names, ", "), ")"));
}

absl::StatusOr<std::shared_ptr<const Scene>> SharedScene(const std::string& name, uint64_t seed,
                                                         int threads) {
  struct Entry {
    std::string name;
    uint64_t seed;
    std::shared_ptr<const Scene> scene;
  };
  static constexpr size_t kCapacity = 4;
  static std::mutex* const mutex = new std::mutex();
  static std::list<Entry>* const cache = new std::list<Entry>();
  std::lock_guard<std::mutex> lock(*mutex);
  for (auto it = cache->begin(); it != cache->end(); ++it) {
    if (it->name == name && it->seed == seed) {
      cache->splice(cache->begin(), *cache, it);  // most recently used first
      return cache->front().scene;
    }
  }
  absl::StatusOr<Scene> scene = MakeScene(name, seed, threads);
  if (!scene.ok()) return scene.status();
  cache->push_front({name, seed, std::make_shared<const Scene>(*std::move(scene))});
  if (cache->size() > kCapacity) cache->pop_back();
  return cache->front().scene;
}

}  // namespace fd::scenegen

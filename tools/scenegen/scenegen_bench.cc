// Scene generator benchmark: milliseconds per frame for ray tracing plus
// 8-bit encoding (BM_RenderFrame) and for writing the six PNGs of a frame
// (BM_WritePngs), at 128x128 and 512x512 with 1 and 2 threads, and the
// one-off scene build (BVH + irradiance volume, BM_BuildScene).
//
//   build/<dir>/tools/scenegen/fd_scenegen_bench --benchmark_min_time=2
#include <benchmark/benchmark.h>

#include <cstdlib>
#include <filesystem>
#include <string>

#include "tools/scenegen/encoding.h"
#include "tools/scenegen/parallel.h"
#include "tools/scenegen/renderer.h"
#include "tools/scenegen/scenes.h"
#include "tools/scenegen/sequence.h"

namespace fd::scenegen {
namespace {

const Scene& CachedScene(const std::string& name) { return **SharedScene(name, 0); }

// Args: {scene (0 = street, 1 = room), threads}: building the BVH and the
// irradiance volume, once per generator run.
void BM_BuildScene(benchmark::State& state) {
  const std::string name = state.range(0) == 0 ? "street" : "room";
  for (auto _ : state) {
    absl::StatusOr<Scene> scene = MakeScene(name, 0, static_cast<int>(state.range(1)));
    benchmark::DoNotOptimize(scene);
  }
  state.SetLabel(name);
}
BENCHMARK(BM_BuildScene)
    ->ArgsProduct({{0, 1}, {1, 2}})
    ->ArgNames({"scene", "threads"})
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();

// Args: {scene (0 = street, 1 = room), size, threads}.
void BM_RenderFrame(benchmark::State& state) {
  const Scene& scene = CachedScene(state.range(0) == 0 ? "street" : "room");
  RenderSettings settings;
  settings.width = settings.height = static_cast<int>(state.range(1));
  settings.threads = static_cast<int>(state.range(2));
  const EncodingParams params{scene.lighting.exposure, scene.near_plane};
  int frame = 0;
  for (auto _ : state) {
    // Walk the camera so the timing averages over different views.
    const FrameBuffers buffers =
        RenderFrame(scene, scene.camera_path.At(frame * 8), frame, settings);
    EncodedFrame encoded = EncodeFrame(buffers, params);
    benchmark::DoNotOptimize(encoded);
    ++frame;
  }
  state.SetLabel(scene.name);
}
BENCHMARK(BM_RenderFrame)
    ->ArgsProduct({{0, 1}, {128, 512}, {1, 2}})
    ->ArgNames({"scene", "size", "threads"})
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();

// Args: {size, threads}: writes the six PNGs of one street frame.
void BM_WritePngs(benchmark::State& state) {
  const Scene& scene = CachedScene("street");
  RenderSettings settings;
  settings.width = settings.height = static_cast<int>(state.range(0));
  settings.threads = 2;
  const EncodedFrame encoded = EncodeFrame(RenderFrame(scene, scene.camera_path.At(0), 0, settings),
                                           {scene.lighting.exposure, scene.near_plane});
  const std::string dir = (std::filesystem::temp_directory_path() / "fd_scenegen_bench").string();
  std::filesystem::create_directories(dir);
  const int threads = static_cast<int>(state.range(1));
  for (auto _ : state) {
    ParallelFor(kNumBuffers, threads, [&](int k) {
      const absl::Status s = WritePng(dir + "/" + kBufferNames[k] + ".png", encoded[k]);
      if (!s.ok()) std::abort();
    });
  }
  std::filesystem::remove_all(dir);
}
BENCHMARK(BM_WritePngs)
    ->ArgsProduct({{128, 512}, {1, 2}})
    ->ArgNames({"size", "threads"})
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();

}  // namespace
}  // namespace fd::scenegen

BENCHMARK_MAIN();

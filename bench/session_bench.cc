// Aggregate frames/s of the FrameScheduler on the tiny golden model
// (fd_pipeline/model, or $FD_GOLDEN_DIR/fd_pipeline/model) for 1, 2, 4 and 8
// concurrent sessions in both batching modes. Each session renders its
// frames back to back (the next frame is enqueued from the previous frame's
// callback, like a client that waits for each frame). Not a test: nothing
// is asserted; results go to docs/BENCHMARKS.md.
//
//   build/<dir>/bench/fd_session_bench [frames_per_session=8] [steps=3]
//       [threads=2] [width=80] [height=64]
#include <torch/torch.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "absl/synchronization/mutex.h"
#include "model/environment.h"
#include "session/clock.h"
#include "session/frame_scheduler.h"
#include "tests/testing/golden.h"

namespace fd::session {
namespace {

FrameGBuffer MakeGBuffer(int64_t h, int64_t w, uint64_t seed) {
  torch::Generator g = at::make_generator<at::CPUGeneratorImpl>(seed);
  FrameGBuffer gb;
  gb.basecolor = torch::randint(0, 256, {h, w, 3}, g, torch::kUInt8);
  gb.normals = torch::rand({h, w, 3}, g);
  gb.depth = torch::rand({h, w}, g);
  gb.roughness = torch::rand({h, w}, g);
  gb.metallic = torch::rand({h, w}, g);
  return gb;
}

// Seconds to render `frames` frames for each of `sessions` sessions.
double Run(std::shared_ptr<const model::Environment> env, BatchingMode mode, int sessions,
           int frames, uint32_t steps, uint32_t width, uint32_t height) {
  FrameSchedulerOptions options;
  options.environment = "tiny";
  options.mode = mode;
  options.max_batch_size = 8;
  options.max_queue_delay = absl::Milliseconds(1);
  FrameScheduler scheduler(std::make_unique<ModelFramePipeline>(env), options);
  std::vector<std::shared_ptr<Session>> all;
  for (int i = 0; i < sessions; ++i) {
    SessionSettings s;
    s.environment = "tiny";
    s.width = width;
    s.height = height;
    s.seed = 1000 + i;
    s.steps = steps;
    s.sky_mode = SkyMode::kPreviousOutput;
    all.push_back(std::make_shared<Session>("s" + std::to_string(i), "bench",
                                            *SessionState::StartFromGBufferOnly(s),
                                            RealClock::Get()));
  }
  absl::Mutex mu;
  int remaining = sessions * frames;
  std::function<void(int, int)> enqueue = [&](int i, int f) {
    FrameJob job;
    job.session = all[i];
    job.frame_index = f;
    job.gbuffer = MakeGBuffer(height, width, i * 100000 + f);
    job.done = [&, i, f](absl::StatusOr<FrameResult> r) {
      if (!r.ok()) {
        std::fprintf(stderr, "frame failed: %s\n", r.status().ToString().c_str());
        std::exit(1);
      }
      if (f + 1 < frames) enqueue(i, f + 1);
      absl::MutexLock lock(&mu);
      --remaining;
    };
    if (!scheduler.Enqueue(std::move(job)).ok()) std::exit(1);
  };
  const auto start = std::chrono::steady_clock::now();
  for (int i = 0; i < sessions; ++i) enqueue(i, 0);
  {
    absl::MutexLock lock(&mu);
    mu.Await(absl::Condition(
        +[](int* n) { return *n == 0; }, &remaining));
  }
  const auto end = std::chrono::steady_clock::now();
  return std::chrono::duration<double>(end - start).count();
}

}  // namespace
}  // namespace fd::session

int main(int argc, char** argv) {
  using namespace fd::session;
  const int frames = argc > 1 ? std::atoi(argv[1]) : 8;
  const uint32_t steps = argc > 2 ? std::atoi(argv[2]) : 3;
  const int threads = argc > 3 ? std::atoi(argv[3]) : 2;
  const uint32_t width = argc > 4 ? std::atoi(argv[4]) : 80;
  const uint32_t height = argc > 5 ? std::atoi(argv[5]) : 64;
  at::set_num_threads(threads);
  auto env = fd::model::LoadEnvironment(fd::testing::GoldenPath("fd_pipeline/model"));
  if (!env.ok()) {
    std::fprintf(stderr, "%s\n", env.status().ToString().c_str());
    return 1;
  }
  std::printf("tiny model, %ux%u, %u steps UniPC, %d frames/session, %d torch threads\n", width,
              height, steps, frames, threads);
  std::printf("%-12s %8s %10s %10s\n", "mode", "sessions", "seconds", "frames/s");
  Run(*env, BatchingMode::kWholeFrame, 1, 2, steps, width, height);  // warm-up
  for (BatchingMode mode : {BatchingMode::kWholeFrame, BatchingMode::kStepLevel}) {
    for (int sessions : {1, 2, 4, 8}) {
      const double seconds = Run(*env, mode, sessions, frames, steps, width, height);
      std::printf("%-12s %8d %10.2f %10.2f\n",
                  mode == BatchingMode::kWholeFrame ? "whole-frame" : "step-level", sessions,
                  seconds, sessions * frames / seconds);
      std::fflush(stdout);
    }
  }
  return 0;
}

// Aggregate frames/s of the FrameBatcher on the tiny golden model
// (fd_pipeline/model, or $FD_GOLDEN_DIR/fd_pipeline/model), or on a preset of
// model/presets/presets.h (--preset tiny|small|sd15, random weights, made in a
// temporary folder), or on any environment folder (--checkpoint DIR), for 1, 2, 4 and 8
// concurrent sessions in both batching modes. Each session renders its
// frames back to back (the next frame is enqueued from the previous frame's
// callback, like a client that waits for each frame). Not a test: nothing
// is asserted; results go to docs/BENCHMARKS.md.
//
//   build/<dir>/bench/fd_session_bench [frames_per_session=8] [steps=3]
//       [threads=1] [width=80] [height=64] [--workers N] [--json FILE]
//       [--preset NAME | --checkpoint DIR] [--batch_invariant]
//
// threads: LibTorch threads of each batcher worker (default 1: under the
// PASSIVE OpenMP policy two threads were slower for every model here, see
// docs/BENCHMARKS.md); --workers: batcher workers
// (FrameBatcherOptions::workers, default 1), e.g. --workers 2 with 1
// thread each runs two batches at once on 2 cores (the server's CPU default).
// --batch_invariant: the pipeline runs convolutions and linear layers sample
// by sample (FramePipelineOptions::batch_invariant, the server's
// --batch_invariant), to measure what bitwise batch independence costs.
//
// Memory: each row also gives the process's peak resident set during the
// run (VmHWM, reset before it through /proc/self/clear_refs), so the growth
// from 1 to N sessions is the working memory a concurrent session adds
// (batched activations, in-flight inputs); and the state an idle session
// keeps between frames (Session::MemoryBytes: previous output and
// basecolor, once a frame was rendered), at this size and at 512x512.
// --json writes the settings and every row as one JSON object
// (bench/run_benchmarks.py collects it).
#include <torch/torch.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "absl/synchronization/mutex.h"
#include "bench/golden_data.h"
#include "bench/preset_checkpoint.h"
#include "model/pipeline/environment.h"
#include "model/runtime/cpu_runtime.h"
#include "nlohmann/json.hpp"
#include "session/clock.h"
#include "session/frame_batcher.h"

namespace fd::session {
namespace {

FrameGBuffer MakeGBuffer(int64_t h, int64_t w, uint64_t seed) {
  torch::Generator g = at::make_generator<at::CPUGeneratorImpl>(seed);
  FrameGBuffer gb;
  // The server hands the batcher decoded images (ImageBuffers); these share
  // the random tensors' storage.
  gb.basecolor = *BufferFromTensor(torch::randint(0, 256, {h, w, 3}, g, torch::kUInt8));
  gb.normals = *BufferFromTensor(torch::rand({h, w, 3}, g));
  gb.depth = *BufferFromTensor(torch::rand({h, w}, g));
  gb.roughness = *BufferFromTensor(torch::rand({h, w}, g));
  gb.metallic = *BufferFromTensor(torch::rand({h, w}, g));
  return gb;
}

// Peak resident set size of this process (VmHWM) in bytes, -1 if unknown.
int64_t PeakRssBytes() {
  std::ifstream status("/proc/self/status");
  std::string key;
  while (status >> key) {
    if (key == "VmHWM:") {
      int64_t kib = 0;
      status >> kib;
      return kib * 1024;
    }
    status.ignore(1 << 20, '\n');
  }
  return -1;
}

// Resets VmHWM to the current RSS (Linux >= 4.0); false if not possible.
bool ResetPeakRss() {
  std::ofstream clear("/proc/self/clear_refs");
  clear << "5";
  clear.flush();
  return static_cast<bool>(clear);
}

struct RunStats {
  double seconds = 0;
  size_t state_bytes_per_session = 0;  // Session::MemoryBytes after the run
};

// Renders `frames` frames for each of `sessions` sessions.
struct BenchConfig {
  int frames = 8;
  uint32_t steps = 3;
  int threads = 2;  // LibTorch threads per batcher worker
  int workers = 1;
  uint32_t width = 80;
  uint32_t height = 64;
  bool batch_invariant = false;
};

RunStats Run(std::shared_ptr<const model::Environment> env, BatchingMode mode, int sessions,
             const BenchConfig& config) {
  const int frames = config.frames;
  const uint32_t steps = config.steps, width = config.width, height = config.height;
  FrameBatcherOptions options;
  options.environment = "tiny";
  options.mode = mode;
  options.max_batch_size = 8;
  options.max_queue_delay = absl::Milliseconds(1);
  options.workers = config.workers;
  options.threads_per_worker = config.threads;
  model::FramePipelineOptions pipeline_options;
  pipeline_options.batch_invariant = config.batch_invariant;
  FrameBatcher batcher(std::make_unique<ModelFramePipeline>(env, pipeline_options), options);
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
    if (!batcher.Enqueue(std::move(job)).ok()) std::exit(1);
  };
  const auto start = std::chrono::steady_clock::now();
  for (int i = 0; i < sessions; ++i) enqueue(i, 0);
  {
    absl::MutexLock lock(&mu);
    mu.Await(absl::Condition(
        +[](int* n) { return *n == 0; }, &remaining));
  }
  const auto end = std::chrono::steady_clock::now();
  RunStats stats;
  stats.seconds = std::chrono::duration<double>(end - start).count();
  stats.state_bytes_per_session = all.front()->MemoryBytes();
  return stats;
}

}  // namespace
}  // namespace fd::session

int main(int argc, char** argv) {
  // As framediffuser-server: OpenMP threads sleep when idle (may re-execute).
  fd::model::UseBoundedOpenMpSpin(argv);
  using namespace fd::session;
  std::string json_path;
  std::string preset;      // a model/presets/presets.h preset, made at start
  std::string checkpoint;  // an environment folder
  int workers = 1;
  bool batch_invariant = false;
  std::vector<std::string> positional;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (arg == "--json" && i + 1 < argc) {
      json_path = argv[++i];
    } else if (arg == "--workers" && i + 1 < argc) {
      workers = std::atoi(argv[++i]);
    } else if (arg.rfind("--workers=", 0) == 0) {
      workers = std::atoi(arg.c_str() + 10);
    } else if (arg.rfind("--json=", 0) == 0) {
      json_path = arg.substr(7);
    } else if (arg == "--preset" && i + 1 < argc) {
      preset = argv[++i];
    } else if (arg == "--checkpoint" && i + 1 < argc) {
      checkpoint = argv[++i];
    } else if (arg == "--batch_invariant") {
      batch_invariant = true;
    } else if (arg.rfind("--", 0) == 0) {
      std::fprintf(stderr,
                   "usage: fd_session_bench [frames_per_session=8] [steps=3] [threads=1] "
                   "[width=80] [height=64] [--workers N] [--json FILE]\n"
                   "       [--preset tiny|small|sd15 | --checkpoint DIR] [--batch_invariant]\n");
      return arg == "--help" ? 0 : 2;
    } else {
      positional.push_back(arg);
    }
  }
  auto arg_or = [&](size_t i, int fallback) {
    return positional.size() > i ? std::atoi(positional[i].c_str()) : fallback;
  };
  const int frames = arg_or(0, 8);
  const uint32_t steps = arg_or(1, 3);
  const int threads = arg_or(2, 1);
  const uint32_t width = arg_or(3, 80);
  const uint32_t height = arg_or(4, 64);
  if (workers < 1) {
    std::fprintf(stderr, "--workers: expected >= 1\n");
    return 2;
  }
  const BenchConfig config{frames, steps, threads, workers, width, height, batch_invariant};
  at::set_num_threads(threads);
  const std::string malloc_tuning = fd::model::TuneMallocForInference();
  const std::string blas_threads = fd::model::UseSingleThreadedBlas();
  if (!preset.empty() && !checkpoint.empty()) {
    std::fprintf(stderr, "--preset and --checkpoint: give one\n");
    return 2;
  }
  std::string model_name = "tiny golden (fd_pipeline/model)";
  std::string model_dir = fd::bench::BenchGoldenPath("fd_pipeline/model");
  if (!preset.empty()) {
    absl::StatusOr<std::string> dir = fd::bench::PresetCheckpointDir(preset);
    if (!dir.ok()) {
      std::fprintf(stderr, "--preset: %s\n", dir.status().ToString().c_str());
      return 2;
    }
    model_name = preset + " preset (random weights, seed 0)";
    model_dir = *dir;
  } else if (!checkpoint.empty()) {
    model_name = checkpoint;
    model_dir = checkpoint;
  }
  auto env = fd::model::LoadEnvironment(model_dir);
  if (!env.ok()) {
    std::fprintf(stderr, "%s\n", env.status().ToString().c_str());
    return 1;
  }
  // The state an idle session keeps: previous output + previous basecolor.
  constexpr size_t kStateBytes512 = 2 * 512 * 512 * 3;
  const char* coretype = std::getenv("OPENBLAS_CORETYPE");
  std::printf(
      "%s, %ux%u, %u steps UniPC, %d frames/session, %d batcher worker(s) x %d "
      "torch threads%s, OPENBLAS_CORETYPE=%s, %s, %s\n",
      model_name.c_str(), width, height, steps, frames, workers, threads,
      batch_invariant ? ", batch-invariant" : "", coretype ? coretype : "(unset)",
      malloc_tuning.c_str(), blas_threads.c_str());
  std::printf("%-12s %8s %10s %10s %12s %14s\n", "mode", "sessions", "seconds", "frames/s",
              "peak_rss_MB", "state_KB/sess");
  BenchConfig warmup = config;
  warmup.frames = 2;
  Run(*env, BatchingMode::kWholeFrame, 1, warmup);
  nlohmann::json rows = nlohmann::json::array();
  for (BatchingMode mode : {BatchingMode::kWholeFrame, BatchingMode::kStepLevel}) {
    for (int sessions : {1, 2, 4, 8}) {
      const bool peak_known = ResetPeakRss();
      const RunStats stats = Run(*env, mode, sessions, config);
      const int64_t peak = peak_known ? PeakRssBytes() : -1;
      const char* mode_name = mode == BatchingMode::kWholeFrame ? "whole-frame" : "step-level";
      std::printf("%-12s %8d %10.2f %10.2f %12.1f %14.1f\n", mode_name, sessions, stats.seconds,
                  sessions * frames / stats.seconds, peak >= 0 ? peak / 1048576.0 : -1.0,
                  stats.state_bytes_per_session / 1024.0);
      std::fflush(stdout);
      rows.push_back({{"mode", mode_name},
                      {"sessions", sessions},
                      {"seconds", stats.seconds},
                      {"frames_per_second", sessions * frames / stats.seconds},
                      {"peak_rss_bytes", peak},
                      {"state_bytes_per_session", stats.state_bytes_per_session}});
    }
  }
  std::printf("idle session state at 512x512: %.2f MB (previous output + basecolor, uint8 RGB)\n",
              kStateBytes512 / 1048576.0);
  if (!json_path.empty()) {
    const nlohmann::json out = {{"benchmark", "fd_session_bench"},
                                {"settings",
                                 {{"model", model_name},
                                  {"width", width},
                                  {"height", height},
                                  {"steps", steps},
                                  {"frames_per_session", frames},
                                  {"threads", threads},
                                  {"workers", workers},
                                  {"batch_invariant", batch_invariant},
                                  {"openblas_coretype", coretype ? coretype : ""},
                                  {"malloc", malloc_tuning},
                                  {"blas", blas_threads}}},
                                {"rows", rows},
                                {"idle_state_bytes_512x512", kStateBytes512}};
    std::ofstream file(json_path);
    file << out.dump(2) << "\n";
    if (!file) {
      std::fprintf(stderr, "--json: cannot write %s\n", json_path.c_str());
      return 1;
    }
  }
  return 0;
}

// fd_trainer_bench: optimizer steps/s of every trainer stage (trainer/) for
// model presets x training sizes x intra-op threads, the loader's wait
// fraction, and stage 3's generation cost per frame. Not a test: nothing is
// asserted. The data are framediffuser-scenegen street sequences rendered
// into a temporary folder at the training size.
//
//   fd_trainer_bench [--presets tiny,small] [--sizes 64,128] [--threads 1,2]
//                    [--replicas 1,2] [--gradient_checkpointing 0,1]
//                    [--steps 20] [--warmup 3] [--batch 4] [--json FILE]
// (--replicas R: each batch split over R single-threaded copies of the
// networks, gradients summed; rows with R > 1 run with 1 intra-op thread.
// --gradient_checkpointing 0,1: each configuration without and with it.)
// "peak MiB": the process's peak resident memory during a stage's timed
// steps (VmHWM, reset before them through /proc/self/clear_refs after
// malloc_trim), which includes the networks, the optimizer state and the
// data loader, so compare rows, not absolute values.
//
// Results and the command that produced them: docs/BENCHMARKS.md
// ("Trainer (CPU)").
#include <malloc.h>
#include <stdlib.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <string>
#include <tuple>
#include <vector>

#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"
#include "model/runtime/cpu_runtime.h"
#include "tools/scenegen/sequence.h"
#include "trainer/trainer.h"

namespace {

namespace fs = std::filesystem;
using fd::trainer::Stage;

struct Flags {
  std::vector<std::string> presets = {"tiny", "small"};
  std::vector<int> sizes = {64, 128};
  std::vector<int> threads = {1, 2};
  std::vector<int> replicas = {1};
  std::vector<int> checkpointing = {0};
  int steps = 20;
  int warmup = 3;
  int batch = 4;
  std::string json;
};

bool ParseInts(const std::string& text, std::vector<int>* out, int min = 1) {
  out->clear();
  for (absl::string_view part : absl::StrSplit(text, ',')) {
    int v = 0;
    if (!absl::SimpleAtoi(part, &v) || v < min) return false;
    out->push_back(v);
  }
  return !out->empty();
}

bool ParseFlags(int argc, char** argv, Flags* f) {
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    const std::string value = i + 1 < argc ? argv[i + 1] : "";
    bool ok = true;
    if (arg == "--presets") {
      f->presets = absl::StrSplit(value, ',');
    } else if (arg == "--sizes") {
      ok = ParseInts(value, &f->sizes);
    } else if (arg == "--threads") {
      ok = ParseInts(value, &f->threads);
    } else if (arg == "--replicas") {
      ok = ParseInts(value, &f->replicas);
    } else if (arg == "--gradient_checkpointing") {
      ok = ParseInts(value, &f->checkpointing, 0);
    } else if (arg == "--steps") {
      ok = absl::SimpleAtoi(value, &f->steps) && f->steps > 0;
    } else if (arg == "--warmup") {
      ok = absl::SimpleAtoi(value, &f->warmup) && f->warmup >= 0;
    } else if (arg == "--batch") {
      ok = absl::SimpleAtoi(value, &f->batch) && f->batch > 0;
    } else if (arg == "--json") {
      f->json = value;
    } else {
      std::fprintf(stderr, "unknown flag %s\n", arg.c_str());
      return false;
    }
    if (!ok) {
      std::fprintf(stderr, "bad value for %s\n", arg.c_str());
      return false;
    }
    ++i;
  }
  return true;
}

// Starts a new peak-memory window: returns freed heap to the system, then
// resets VmHWM to the current resident size (Linux clear_refs value 5).
void ResetPeakMemory() {
  malloc_trim(0);
  std::ofstream("/proc/self/clear_refs") << "5";
}

// The peak resident memory since ResetPeakMemory, in MiB (0 if unknown).
double PeakMemoryMib() {
  std::ifstream status("/proc/self/status");
  std::string line;
  while (std::getline(status, line)) {
    if (line.rfind("VmHWM:", 0) == 0) return std::stod(line.substr(6)) / 1024.0;
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  fd::model::UseBoundedOpenMpSpin(argv);
  fd::model::UseSingleThreadedBlas();
  Flags flags;
  if (!ParseFlags(argc, argv, &flags)) return 2;
  std::string tmp = (fs::temp_directory_path() / "fd_trainer_bench_XXXXXX").string();
  if (mkdtemp(tmp.data()) == nullptr) return 1;
  nlohmann::json rows = nlohmann::json::array();
  std::printf("%-6s %5s %7s %8s %4s %-12s %9s %9s %7s %9s\n", "preset", "size", "threads",
              "replicas", "ckpt", "stage", "steps/s", "ms/step", "wait", "peak MiB");
  for (int size : flags.sizes) {
    const std::string data = tmp + "/data" + std::to_string(size);
    for (int s = 0; s < 2; ++s) {
      fd::scenegen::GeneratorOptions gen;
      gen.frames = 12;
      gen.width = gen.height = size;
      gen.seed = static_cast<uint64_t>(s);
      gen.out_dir = data + "/seq" + std::to_string(s);
      if (!fd::scenegen::GenerateSequence(gen).ok()) return 1;
    }
    for (const std::string& preset : flags.presets) {
      std::vector<std::tuple<int, int, int>> configs;  // (threads, replicas, checkpointing)
      for (int checkpointing : flags.checkpointing) {
        for (int threads : flags.threads) configs.push_back({threads, 1, checkpointing});
        for (int replicas : flags.replicas) {
          if (replicas > 1) configs.push_back({1, replicas, checkpointing});
        }
      }
      for (const auto& [threads, replicas, checkpointing] : configs) {
        fd::trainer::TrainerOptions o;
        o.replicas = replicas;
        o.gradient_checkpointing = checkpointing != 0;
        o.data_dirs = {data};
        o.out_dir = tmp + "/out";
        fs::remove_all(o.out_dir);
        o.preset = preset;
        o.width = o.height = size;
        o.batch_size = flags.batch;
        o.threads = threads;
        o.progress_bar = false;
        o.log_every = 1000000;
        o.validation_frames = 1;
        o.selfcond_steps = 10;
        o.selfcond_count = 4;
        o.selfcond_every = 1000000;
        for (int st = 0; st < fd::trainer::kStageCount; ++st) {
          o.schedule[st] = fd::trainer::DefaultSchedule(static_cast<Stage>(st));
          o.schedule[st].steps = flags.steps + flags.warmup;
          o.schedule[st].warmup = 1;
        }
        absl::StatusOr<std::unique_ptr<fd::trainer::Trainer>> trainer =
            fd::trainer::Trainer::Create(o);
        if (!trainer.ok()) {
          std::fprintf(stderr, "%s\n", std::string(trainer.status().message()).c_str());
          return 1;
        }
        fd::trainer::Trainer& t = **trainer;
        for (int st = 0; st < fd::trainer::kStageCount; ++st) {
          const Stage stage = static_cast<Stage>(st);
          if (!t.BeginStage(stage).ok()) return 1;
          double generate_ms_per_frame = 0;
          if (stage == Stage::kSelfConditioning) {
            const auto start = std::chrono::steady_clock::now();
            if (!t.GeneratePool().ok()) return 1;
            generate_ms_per_frame =
                std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
                    .count() /
                static_cast<double>(t.pool().size());
          }
          for (int i = 0; i < flags.warmup; ++i) {
            if (!t.TrainStep().ok()) return 1;
          }
          ResetPeakMemory();
          const auto start = std::chrono::steady_clock::now();
          for (int i = 0; i < flags.steps; ++i) {
            if (!t.TrainStep().ok()) return 1;
          }
          const double seconds =
              std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
          const double rate = flags.steps / seconds;
          const double peak_mib = PeakMemoryMib();
          std::printf("%-6s %5d %7d %8d %4d %-12s %9.2f %9.1f %6.1f%% %9.0f\n", preset.c_str(),
                      size, threads, replicas, checkpointing, fd::trainer::StageName(stage), rate,
                      1000.0 / rate, 100.0 * t.loader_wait_fraction(), peak_mib);
          std::fflush(stdout);
          nlohmann::json row = {{"preset", preset},
                                {"size", size},
                                {"threads", threads},
                                {"replicas", replicas},
                                {"gradient_checkpointing", checkpointing != 0},
                                {"peak_rss_mib", peak_mib},
                                {"batch", flags.batch},
                                {"stage", fd::trainer::StageName(stage)},
                                {"steps_per_s", rate},
                                {"ms_per_step", 1000.0 / rate},
                                {"loader_wait_fraction", t.loader_wait_fraction()}};
          if (stage == Stage::kSelfConditioning) {
            row["generate_ms_per_frame"] = generate_ms_per_frame;
            std::printf("%-6s %5d %7d %8d %4d %-12s %9s %9.1f ms per generated frame (10 steps)\n",
                        preset.c_str(), size, threads, replicas, checkpointing, "", "",
                        generate_ms_per_frame);
          }
          rows.push_back(row);
          if (!t.EndStage().ok()) return 1;
        }
      }
    }
  }
  fs::remove_all(tmp);
  if (!flags.json.empty()) std::ofstream(flags.json) << nlohmann::json{{"rows", rows}}.dump(2);
  return 0;
}

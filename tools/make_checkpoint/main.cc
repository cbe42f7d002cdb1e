// framediffuser-make-checkpoint: writes a random-weight FrameDiffuser
// checkpoint (see model/presets/presets.h for the layout and the presets).
//
//   framediffuser-make-checkpoint --preset tiny --out /tmp/fd_tiny [--seed 0]
//       [--dtype float32|float16|bfloat16] [--lora_rank R]
#include <torch/torch.h>

#include <cstdio>
#include <cstdlib>
#include <string>

#include "absl/strings/numbers.h"
#include "absl/strings/str_join.h"
#include "model/presets/presets.h"

namespace {

constexpr int kExitUsage = 2;

void PrintUsage() {
  std::printf(
      "usage: framediffuser-make-checkpoint --preset NAME --out DIR [--seed N]\n"
      "           [--dtype float32|float16|bfloat16] [--lora_rank R]\n"
      "presets: %s (sd15 = the real Stable Diffusion 1.5 shapes, ~2 GB of weights\n"
      "in float16, needs ~7 GB of memory while writing)\n",
      absl::StrJoin(fd::model::CheckpointPresetNames(), ", ").c_str());
}

}  // namespace

int main(int argc, char** argv) {
  fd::model::MakeCheckpointOptions options;
  for (int i = 1; i < argc; ++i) {
    std::string flag = argv[i];
    std::string value;
    if (flag == "--help" || flag == "-h") {
      PrintUsage();
      return 0;
    }
    if (const size_t eq = flag.find('='); eq != std::string::npos) {
      value = flag.substr(eq + 1);
      flag = flag.substr(0, eq);
    } else if (i + 1 < argc) {
      value = argv[++i];
    } else {
      std::fprintf(stderr, "error: %s needs a value\n", flag.c_str());
      return kExitUsage;
    }
    bool ok = true;
    if (flag == "--preset") {
      options.preset = value;
    } else if (flag == "--out") {
      options.out_dir = value;
    } else if (flag == "--seed") {
      ok = absl::SimpleAtoi(value, &options.seed);
    } else if (flag == "--lora_rank") {
      ok = absl::SimpleAtoi(value, &options.lora_rank);
    } else if (flag == "--dtype") {
      if (value == "float32") {
        options.dtype = torch::kFloat32;
      } else if (value == "float16") {
        options.dtype = torch::kFloat16;
      } else if (value == "bfloat16") {
        options.dtype = torch::kBFloat16;
      } else {
        ok = false;
      }
    } else {
      std::fprintf(stderr, "error: unknown flag %s\n", flag.c_str());
      PrintUsage();
      return kExitUsage;
    }
    if (!ok) {
      std::fprintf(stderr, "error: bad value '%s' for %s\n", value.c_str(), flag.c_str());
      return kExitUsage;
    }
  }
  if (options.out_dir.empty()) {
    std::fprintf(stderr, "error: --out is required\n");
    PrintUsage();
    return kExitUsage;
  }
  const absl::Status status = fd::model::MakeCheckpoint(options);
  if (!status.ok()) {
    std::fprintf(stderr, "error: %s\n", std::string(status.message()).c_str());
    return 1;
  }
  std::printf("wrote %s checkpoint to %s\n", options.preset.c_str(), options.out_dir.c_str());
  return 0;
}

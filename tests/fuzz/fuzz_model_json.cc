// Fuzz target: the JSON files of a checkpoint folder and of the authors'
// layout -> their parsers: UNet / ControlNet / VAE / CLIP text config.json
// (and the block layouts built from them), scheduler_config.json,
// environment.json and inference_configs.json.
//
// Input: byte 0 picks the parser (mod 7), the rest is the file's text.
// Properties: no crash, no hang; an error is INVALID_ARGUMENT (malformed) or
// UNIMPLEMENTED (a valid diffusers setting this port does not support, as
// model_configs.h documents), names the file and is bounded in size (a long
// client-written string is quoted bounded).
#include <cstddef>
#include <cstdint>
#include <string>

#include "model/networks/model_configs.h"
#include "model/pipeline/environment.h"
#include "model/schedulers/scheduler.h"
#include "model/schedulers/scheduler_settings.h"
#include "tests/fuzz/fuzz_check.h"

namespace {

constexpr char kSource[] = "fuzz/config.json";

// INVALID_ARGUMENT or UNIMPLEMENTED, bounded.
void CheckConfigError(const absl::Status& status) {
  fd::fuzz::CheckError(status,
                       status.code() == absl::StatusCode::kUnimplemented
                           ? absl::StatusCode::kUnimplemented
                           : absl::StatusCode::kInvalidArgument,
                       "");
}

void CheckParseError(const absl::Status& status) {
  if (status.ok()) return;
  CheckConfigError(status);
  FD_FUZZ_CHECK(status.message().find(kSource) != absl::string_view::npos, "names the file");
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size < 1) return 0;
  const std::string text(reinterpret_cast<const char*>(data) + 1, size - 1);
  switch (data[0] % 7) {
    case 0: {
      auto config = fd::model::ParseUNet2DConditionConfig(text, kSource);
      CheckParseError(config.status());
      if (config.ok()) {
        auto layout = fd::model::ComputeUNetLayout(*config);
        if (!layout.ok()) CheckConfigError(layout.status());
      }
      break;
    }
    case 1: {
      auto config = fd::model::ParseControlNetConfig(text, kSource);
      CheckParseError(config.status());
      if (config.ok()) {
        auto layout = fd::model::ComputeControlNetLayout(*config);
        if (!layout.ok()) CheckConfigError(layout.status());
        fd::model::DetectControlNetEmbedding(*config);
      }
      break;
    }
    case 2:
      CheckParseError(fd::model::ParseAutoencoderKLConfig(text, kSource).status());
      break;
    case 3:
      CheckParseError(fd::model::ParseCLIPTextConfig(text, kSource).status());
      break;
    case 4: {
      // What loading does with scheduler_config.json: one scheduler per
      // sampler it supports, then a session's timesteps (byte 1: steps).
      auto schedulers =
          fd::model::BuildSchedulers(text, fd::model::SchedulerType::kUniPCMultistep, kSource);
      CheckParseError(schedulers.status());
      if (schedulers.ok()) {
        const int steps = 1 + (size > 1 ? data[1] % 50 : 0);
        for (const auto& [type, scheduler] : *schedulers) {
          auto state = scheduler.NewState(steps);
          if (!state.ok()) CheckConfigError(state.status());
        }
      }
      break;
    }
    case 5:
      CheckParseError(fd::model::ParseEnvironmentSettings(text, kSource).status());
      break;
    default: {
      auto entries = fd::model::ParseInferenceConfigs(text, "/fuzz/base");
      if (!entries.ok()) {
        fd::fuzz::CheckError(entries.status(), absl::StatusCode::kInvalidArgument, "");
      }
      break;
    }
  }
  return 0;
}

#include "model/pipeline/thread_choice.h"

#include <ATen/CPUGeneratorImpl.h>
#include <ATen/Parallel.h>
#include <torch/torch.h>

#include <algorithm>
#include <chrono>
#include <utility>
#include <vector>

#include "base/status_macros.h"
#include "model/pipeline/frame_pipeline.h"

namespace fd::model {
namespace {

double MedianOf(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

// A batch-1 frame at the environment's native size (or the options' size).
PipelineInput CalibrationFrame(const Environment& env, const ThreadChoiceOptions& options) {
  const int64_t h = options.height > 0 ? options.height : env.settings.height;
  const int64_t w = options.width > 0 ? options.width : env.settings.width;
  PipelineInput r = RandomGBufferFrame(h, w, /*seed=*/0);
  r.guidance_scale = 1.0;
  if (!env.prompt_embeds.defined()) {
    // An environment served with per-request embeddings: 77 zero tokens.
    r.prompt_embeds = torch::zeros({1, 77, env.unet->layout().mid_block.cross_attention_dim});
  }
  return r;
}

}  // namespace

PipelineInput RandomGBufferFrame(int64_t height, int64_t width, uint64_t seed) {
  auto gen = at::make_generator<at::CPUGeneratorImpl>(seed);
  auto image = [&](int64_t channels) {
    return at::randint(0, 256, {height, width, channels}, gen, torch::kUInt8);
  };
  PipelineInput r;
  r.previous_frame = image(3);
  r.previous_basecolor = image(3);
  r.basecolor = image(3);
  r.normals = image(3);
  r.depth = image(1);
  r.roughness = image(1);
  r.metallic = image(1);
  r.sky_mode = SkyFillMode::kPreviousOutput;
  return r;
}

absl::StatusOr<ThreadChoice> ChooseIntraOpThreads(std::shared_ptr<const Environment> environment,
                                                  int max_threads,
                                                  const ThreadChoiceOptions& options) {
  ThreadChoice choice;
  if (max_threads <= 1 || !environment->device.is_cpu()) return choice;
  const int caller_threads = at::get_num_threads();
  const PipelineInput frame = CalibrationFrame(*environment, options);
  const int rounds = std::max(1, options.rounds);
  const int counts[2] = {1, max_threads};
  std::vector<double> times[2];
  absl::Status status = absl::OkStatus();
  for (int round = 0; round <= rounds && status.ok(); ++round) {
    for (int k = 0; k < 2 && status.ok(); ++k) {
      FramePipelineOptions options;
      options.intra_op_threads = counts[k];
      FramePipeline pipeline(environment, options);
      absl::StatusOr<std::vector<FrameState>> states = pipeline.Begin({frame});
      if (!states.ok()) {
        status = states.status();
        break;
      }
      FrameState* state = &(*states)[0];
      const auto start = std::chrono::steady_clock::now();
      status = pipeline.Step({state});
      const double ms =
          std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
              .count();
      if (round > 0) times[k].push_back(ms);  // round 0 warms up (oneDNN primitives, allocator)
    }
  }
  at::set_num_threads(caller_threads);
  FD_RETURN_IF_ERROR(status);
  choice.step_ms_one = MedianOf(times[0]);
  choice.step_ms_many = MedianOf(times[1]);
  choice.threads = choice.step_ms_many < choice.step_ms_one ? max_threads : 1;
  return choice;
}

}  // namespace fd::model

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
#include "model/runtime/core_budget.h"

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

double MsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
      .count();
}

struct FrameTimes {
  double ms_without = 0;
  double ms_with = 0;
};

// Median whole frames (Render: Begin, the environment's steps, Finish) of
// `frame` at 1 intra-op thread without and with vae_on_free_core (a second
// thread for the VAE), alternating after one untimed round, as a lone
// session on a 2-core machine runs them (a private budget of 2 cores; the
// ControlNet beside the UNet as chosen). Whole frames, not decodes alone:
// switching a thread's count drops oneDNN's cached primitives
// (at::set_num_threads), which the steps then rebuild; on config B that
// cost more than the faster decode saved. Restores the caller's count.
absl::StatusOr<FrameTimes> TimeVaeOnFreeCore(const std::shared_ptr<const Environment>& environment,
                                             const PipelineInput& frame, int rounds, bool beside) {
  const int caller_threads = at::get_num_threads();
  CoreBudget lone_session(2);
  std::vector<double> times[2];
  absl::Status status = absl::OkStatus();
  for (int round = 0; round <= rounds && status.ok(); ++round) {
    for (int k = 0; k < 2 && status.ok(); ++k) {
      FramePipelineOptions options;
      options.intra_op_threads = 1;
      options.controlnet_beside_unet =
          beside ? ControlNetBeside::kWhenCoreFree : ControlNetBeside::kNever;
      options.vae_on_free_core = k == 1;
      options.core_budget = &lone_session;
      FramePipeline pipeline(environment, options);
      const auto start = std::chrono::steady_clock::now();
      status = pipeline.Render({frame}).status();
      const double ms = MsSince(start);
      if (round > 0) times[k].push_back(ms);
    }
  }
  at::set_num_threads(caller_threads);
  FD_RETURN_IF_ERROR(status);
  return FrameTimes{MedianOf(times[0]), MedianOf(times[1])};
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
  const bool companion = options.companion && CoreBudget::Process().cores() >= 2;
  if ((max_threads <= 1 && !companion) || !environment->device.is_cpu()) return choice;
  const int caller_threads = at::get_num_threads();
  const PipelineInput frame = CalibrationFrame(*environment, options);
  const int rounds = std::max(1, options.rounds);
  struct Candidate {
    int threads;
    bool beside;
  };
  std::vector<Candidate> candidates = {{1, false}};
  if (max_threads > 1) candidates.push_back({max_threads, false});
  if (companion) candidates.push_back({1, true});
  const size_t n = candidates.size();
  std::vector<std::vector<double>> times(n);
  absl::Status status = absl::OkStatus();
  for (int round = 0; round <= rounds && status.ok(); ++round) {
    for (size_t k = 0; k < n && status.ok(); ++k) {
      FramePipelineOptions pipeline_options;
      pipeline_options.intra_op_threads = candidates[k].threads;
      pipeline_options.controlnet_beside_unet =
          candidates[k].beside ? ControlNetBeside::kAlways : ControlNetBeside::kNever;
      FramePipeline pipeline(environment, pipeline_options);
      absl::StatusOr<std::vector<FrameState>> states = pipeline.Begin({frame});
      if (!states.ok()) {
        status = states.status();
        break;
      }
      FrameState* state = &(*states)[0];
      const auto start = std::chrono::steady_clock::now();
      status = pipeline.Step({state});
      const double ms = MsSince(start);
      if (round > 0) times[k].push_back(ms);  // round 0 warms up (oneDNN primitives, allocator)
    }
  }
  at::set_num_threads(caller_threads);
  FD_RETURN_IF_ERROR(status);
  size_t best = 0;
  for (size_t k = 0; k < n; ++k) {
    const double median = MedianOf(times[k]);
    if (candidates[k].beside) {
      choice.step_ms_beside = median;
    } else if (candidates[k].threads > 1) {
      choice.step_ms_many = median;
    } else {
      choice.step_ms_one = median;
    }
    if (median < MedianOf(times[best])) best = k;
  }
  choice.threads = candidates[best].threads;
  choice.controlnet_beside_unet = candidates[best].beside;
  if (companion && choice.threads == 1) {
    FD_ASSIGN_OR_RETURN(const FrameTimes frames, TimeVaeOnFreeCore(environment, frame, rounds,
                                                                   choice.controlnet_beside_unet));
    choice.frame_ms_vae_one = frames.ms_without;
    choice.frame_ms_vae_two = frames.ms_with;
    choice.vae_on_free_core = frames.ms_with < frames.ms_without;
  }
  return choice;
}

}  // namespace fd::model

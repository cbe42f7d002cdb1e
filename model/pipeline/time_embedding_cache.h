// TimeEmbeddingCache: the ControlNet's and the UNet's time embeddings
// (diffusers' `time_proj` + `time_embedding`, the first lines of both
// forwards) per timestep value, so that the denoising loop computes them
// once per environment instead of at every step of every frame. The
// schedules are fixed (10 UniPC steps visit the same 10 timesteps frame
// after frame), so after the first frame every lookup hits.
//
// Each row is computed alone (batch 1), exactly as a batch-1 forward computes
// it: a frame's result does not depend on which rows were cached by which
// batch. Thread-safety: thread-safe (Get may run on several batcher workers).
#ifndef FD_MODEL_PIPELINE_TIME_EMBEDDING_CACHE_H_
#define FD_MODEL_PIPELINE_TIME_EMBEDDING_CACHE_H_

#include <torch/types.h>

#include <cstddef>
#include <cstdint>
#include <map>
#include <mutex>

#include "absl/status/statusor.h"
#include "model/networks/controlnet.h"
#include "model/networks/unet.h"

namespace fd::model {

class TimeEmbeddingCache {
 public:
  // More distinct timesteps than this (a client cycling through many step
  // counts) clear the cache instead of growing it without bound.
  static constexpr size_t kMaxEntries = 4096;

  struct Rows {
    torch::Tensor controlnet;  // [N, 4*C0_controlnet], model dtype and device
    torch::Tensor unet;        // [N, 4*C0_unet]
  };

  // The embeddings of `timesteps` (float32 [N] on the CPU, as
  // Scheduler::CurrentTimesteps returns them), one row per item. The
  // networks must stay the same for the cache's life (one cache per
  // FramePipeline, whose environment is immutable). INTERNAL on torch errors.
  absl::StatusOr<Rows> Get(ControlNetModel& controlnet, UNet2DConditionModel& unet,
                           const torch::Tensor& timesteps);

  size_t size() const;

 private:
  mutable std::mutex mu_;
  std::map<uint32_t, Rows> rows_;  // by the float32 timestep's bits; guarded by mu_
};

}  // namespace fd::model

#endif  // FD_MODEL_PIPELINE_TIME_EMBEDDING_CACHE_H_

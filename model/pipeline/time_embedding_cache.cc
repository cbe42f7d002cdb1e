#include "model/pipeline/time_embedding_cache.h"

#include <torch/torch.h>

#include <cstring>
#include <vector>

#include "base/status_macros.h"

namespace fd::model {
namespace {

uint32_t Bits(float t) {
  uint32_t bits = 0;
  std::memcpy(&bits, &t, sizeof(bits));
  return bits;
}

}  // namespace

absl::StatusOr<TimeEmbeddingCache::Rows> TimeEmbeddingCache::Get(ControlNetModel& controlnet,
                                                                 UNet2DConditionModel& unet,
                                                                 const torch::Tensor& timesteps) {
  const torch::Tensor t = timesteps.to(torch::kCPU, torch::kFloat32).contiguous();
  const float* values = t.data_ptr<float>();
  const int64_t n = t.numel();
  std::vector<torch::Tensor> controlnet_rows(n), unet_rows(n);
  std::vector<int64_t> missing;
  {
    std::lock_guard<std::mutex> lock(mu_);
    for (int64_t i = 0; i < n; ++i) {
      auto it = rows_.find(Bits(values[i]));
      if (it == rows_.end()) {
        missing.push_back(i);
      } else {
        controlnet_rows[i] = it->second.controlnet;
        unet_rows[i] = it->second.unet;
      }
    }
  }
  // Misses are computed outside the lock (two workers may both compute the
  // same row once; the results are equal).
  for (int64_t i : missing) {
    const torch::Tensor one = t.slice(0, i, i + 1);  // [1]
    FD_ASSIGN_OR_RETURN(controlnet_rows[i], controlnet->RunTimeEmbedding(one, 1));
    FD_ASSIGN_OR_RETURN(unet_rows[i], unet->RunTimeEmbedding(one, 1));
    std::lock_guard<std::mutex> lock(mu_);
    if (rows_.size() >= kMaxEntries) rows_.clear();
    rows_.emplace(Bits(values[i]), Rows{controlnet_rows[i], unet_rows[i]});
  }
  if (n == 1) return Rows{controlnet_rows[0], unet_rows[0]};
  return Rows{torch::cat(controlnet_rows, 0), torch::cat(unet_rows, 0)};
}

size_t TimeEmbeddingCache::size() const {
  std::lock_guard<std::mutex> lock(mu_);
  return rows_.size();
}

}  // namespace fd::model

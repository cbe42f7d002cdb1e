// PromptKvCache: the keys and values that cross-attention layers project
// from prompt embeddings, kept across denoising steps and frames. A frame's
// prompt embeddings do not change between its steps (and are usually the
// environment's own for every frame), yet diffusers' Attention projects
// them with to_k / to_v at every step (docs/BENCHMARKS.md, "Step-invariant
// work": 7.7 MFLOP of a 113 MFLOP config-B step).
//
// Use: FramePipeline::Step puts a PromptKvScope on its thread around the
// network calls, naming the per-item prompt tensors whose concatenation
// (along the batch) is the encoder_hidden_states it passes. While the scope
// is active, Attention (model/networks/attention_processor.h) takes each
// item's K and V from the cache (computed alone, at batch 1, with the
// layer's own to_k / to_v, on first use) and concatenates them, instead of
// projecting the concatenated prompt. At batch 1 this is bitwise the
// unscoped forward; in a larger batch each row is the row it has alone.
//
// Entries are keyed by the attention layer and the prompt tensor's identity
// (the cache holds a reference to the tensor, so its storage cannot be
// reused by another tensor while cached) and bounded in bytes.
// Thread-safety: PromptKvCache is thread-safe; a scope belongs to the thread
// that made it.
#ifndef FD_MODEL_NETWORKS_PROMPT_KV_CACHE_H_
#define FD_MODEL_NETWORKS_PROMPT_KV_CACHE_H_

#include <torch/types.h>

#include <cstddef>
#include <cstdint>
#include <functional>
#include <map>
#include <mutex>
#include <utility>
#include <vector>

namespace fd::model {

class PromptKvCache {
 public:
  // Beyond this many bytes of cached K/V the cache is cleared (a client
  // sending new prompt embeddings with every frame must not grow it).
  static constexpr size_t kMaxBytes = size_t{64} << 20;

  using KeyValue = std::pair<torch::Tensor, torch::Tensor>;  // K, V: [1, L, C]

  // K and V of `prompt` ([1, L, D]) for the layer `layer`: cached, or
  // compute() now (outside the lock) and cached.
  KeyValue Get(const void* layer, const torch::Tensor& prompt,
               const std::function<KeyValue()>& compute);

  size_t bytes() const;

 private:
  struct Entry {
    torch::Tensor prompt;  // keeps the key's storage alive
    KeyValue kv;
  };
  mutable std::mutex mu_;
  std::map<std::pair<const void*, const void*>, Entry> entries_;  // guarded by mu_
  size_t bytes_ = 0;                                              // guarded by mu_
};

// RAII: makes `cache` and `rows` the calling thread's prompt K/V source until
// destroyed (see the header comment); scopes nest. `rows`: one [1, L, D]
// tensor per batch row of the encoder_hidden_states the networks get.
class PromptKvScope {
 public:
  PromptKvScope(PromptKvCache* cache, std::vector<torch::Tensor> rows);
  ~PromptKvScope();
  PromptKvScope(const PromptKvScope&) = delete;
  PromptKvScope& operator=(const PromptKvScope&) = delete;

  // The active scope of the calling thread, or nullptr.
  static const PromptKvScope* Current();

  PromptKvCache* cache() const { return cache_; }
  const std::vector<torch::Tensor>& rows() const { return rows_; }

 private:
  PromptKvCache* cache_;
  std::vector<torch::Tensor> rows_;
  const PromptKvScope* previous_;
};

}  // namespace fd::model

#endif  // FD_MODEL_NETWORKS_PROMPT_KV_CACHE_H_

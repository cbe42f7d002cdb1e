#include "model/networks/prompt_kv_cache.h"

namespace fd::model {
namespace {

thread_local const PromptKvScope* current_scope = nullptr;

size_t Bytes(const torch::Tensor& t) { return t.numel() * t.element_size(); }

}  // namespace

PromptKvCache::KeyValue PromptKvCache::Get(const void* layer, const torch::Tensor& prompt,
                                           const std::function<KeyValue()>& compute) {
  const std::pair<const void*, const void*> key(layer, prompt.unsafeGetTensorImpl());
  {
    std::lock_guard<std::mutex> lock(mu_);
    auto it = entries_.find(key);
    if (it != entries_.end()) return it->second.kv;
  }
  KeyValue kv = compute();
  const size_t size = Bytes(kv.first) + Bytes(kv.second);
  std::lock_guard<std::mutex> lock(mu_);
  if (bytes_ + size > kMaxBytes) {
    entries_.clear();
    bytes_ = 0;
  }
  if (entries_.emplace(key, Entry{prompt, kv}).second) bytes_ += size;
  return kv;
}

size_t PromptKvCache::bytes() const {
  std::lock_guard<std::mutex> lock(mu_);
  return bytes_;
}

PromptKvScope::PromptKvScope(PromptKvCache* cache, std::vector<torch::Tensor> rows)
    : cache_(cache), rows_(std::move(rows)), previous_(current_scope) {
  current_scope = this;
}

PromptKvScope::~PromptKvScope() { current_scope = previous_; }

const PromptKvScope* PromptKvScope::Current() { return current_scope; }

}  // namespace fd::model

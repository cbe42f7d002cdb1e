#include "trainer/batch_loader.h"

#include <chrono>
#include <utility>

namespace fd::trainer {

BatchLoader::BatchLoader(const TrainingData& data, const std::vector<GeneratedFrame>& pool,
                         BatchLoaderOptions options, int64_t first_micro_step)
    : data_(data),
      pool_(pool),
      options_(std::move(options)),
      next_to_build_(first_micro_step),
      next_to_return_(first_micro_step) {
  for (int i = 0; i < std::max(1, options_.threads); ++i) workers_.emplace_back([this] { Work(); });
}

BatchLoader::~BatchLoader() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stop_ = true;
  }
  cv_.notify_all();
  for (std::thread& t : workers_) t.join();
}

void BatchLoader::Work() {
  while (true) {
    int64_t step;
    {
      std::unique_lock<std::mutex> lock(mutex_);
      cv_.wait(lock, [&] {
        return stop_ || next_to_build_ < next_to_return_ + std::max(1, options_.prefetch);
      });
      if (stop_) return;
      step = next_to_build_++;
    }
    absl::StatusOr<TrainingBatch> batch =
        BuildBatch(data_, options_.samples, pool_, options_.seed, step * options_.batch_size,
                   options_.batch_size);
    {
      std::lock_guard<std::mutex> lock(mutex_);
      ready_.emplace(step, std::move(batch));
    }
    cv_.notify_all();
  }
}

absl::StatusOr<TrainingBatch> BatchLoader::Next() {
  const auto start = std::chrono::steady_clock::now();
  std::unique_lock<std::mutex> lock(mutex_);
  cv_.wait(lock, [&] { return ready_.count(next_to_return_) > 0; });
  wait_seconds_ += std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  auto it = ready_.find(next_to_return_);
  absl::StatusOr<TrainingBatch> batch = std::move(it->second);
  ready_.erase(it);
  ++next_to_return_;
  lock.unlock();
  cv_.notify_all();
  return batch;
}

}  // namespace fd::trainer

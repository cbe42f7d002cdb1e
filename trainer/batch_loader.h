// Prefetches training batches on background threads so that the optimiser
// step does not wait for sample building (decoding happened once, at load:
// training_data.h; here: offset sampling, noise injection, sky fill,
// irradiance and packing, sample_builder.h).
//
// Batches are produced for consecutive micro-steps first, first + 1, ...;
// batch m holds samples m * batch_size ... and depends only on m (sample
// randomness is per sample index), so the thread that built it and the
// order in which threads finish do not matter: Next() hands them out in
// order. The pool of generated frames is fixed for a loader's lifetime
// (stage 3 makes a new loader after each generation round).
//
// Thread-safety: Next() and the statistics from one thread (the training
// loop); the workers are internal. The destructor stops and joins them.
#ifndef FD_TRAINER_BATCH_LOADER_H_
#define FD_TRAINER_BATCH_LOADER_H_

#include <condition_variable>
#include <cstdint>
#include <map>
#include <mutex>
#include <thread>
#include <vector>

#include "absl/status/statusor.h"
#include "trainer/sample_builder.h"

namespace fd::trainer {

struct BatchLoaderOptions {
  int threads = 1;
  int prefetch = 4;  // batches built ahead of the one being consumed
  int batch_size = 1;
  uint64_t seed = 0;
  SampleOptions samples;
};

class BatchLoader {
 public:
  // `data` and `pool` must outlive the loader (not copied).
  BatchLoader(const TrainingData& data, const std::vector<GeneratedFrame>& pool,
              BatchLoaderOptions options, int64_t first_micro_step);
  ~BatchLoader();
  BatchLoader(const BatchLoader&) = delete;
  BatchLoader& operator=(const BatchLoader&) = delete;

  // The batch of the next micro-step (first_micro_step, then + 1, ...).
  // Errors: whatever building a sample returned (e.g. INVALID_ARGUMENT).
  absl::StatusOr<TrainingBatch> Next();

  // Seconds Next() spent waiting for a batch that was not ready.
  double wait_seconds() const { return wait_seconds_; }

 private:
  void Work();

  const TrainingData& data_;
  const std::vector<GeneratedFrame>& pool_;
  const BatchLoaderOptions options_;
  std::mutex mutex_;
  std::condition_variable cv_;
  int64_t next_to_build_;
  int64_t next_to_return_;
  std::map<int64_t, absl::StatusOr<TrainingBatch>> ready_;
  bool stop_ = false;
  double wait_seconds_ = 0;
  std::vector<std::thread> workers_;
};

}  // namespace fd::trainer

#endif  // FD_TRAINER_BATCH_LOADER_H_

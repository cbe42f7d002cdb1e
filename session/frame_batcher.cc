#include "session/frame_batcher.h"

#include <ATen/Parallel.h>
#include <c10/core/InferenceMode.h>

#include <algorithm>
#include <atomic>
#include <utility>

#include "absl/strings/str_cat.h"

namespace fd::session {

// One frame from Enqueue to its callback. Fields other than `cancelled` are
// touched by one thread at a time (Enqueue, then the worker).
struct FrameBatcher::Item {
  FrameJob job;
  absl::Time enqueued;
  std::atomic<bool> cancelled{false};
  std::optional<model::FrameState> state;
  ImageBuffer basecolor;  // committed as the next previous basecolor
  FrameTimings timings;
};

namespace {

uint64_t NextLatentSource() {
  static std::atomic<uint64_t> next{1};
  return next.fetch_add(1, std::memory_order_relaxed);
}

double Ms(absl::Duration d) { return absl::ToDoubleMilliseconds(d); }

}  // namespace

FrameBatcher::FrameBatcher(std::unique_ptr<FramePipelineInterface> pipeline,
                           FrameBatcherOptions options, FrameBatcherObserver* observer)
    : pipeline_(std::move(pipeline)),
      options_(std::move(options)),
      latent_source_(NextLatentSource()),
      observer_(observer != nullptr ? observer : NoopFrameBatcherObserver::Get()),
      worker_batch_size_(
          std::max(1, (std::max(1, options_.max_batch_size) + std::max(1, options_.workers) - 1) /
                          std::max(1, options_.workers))) {
  const int workers = std::max(1, options_.workers);
  {
    absl::MutexLock lock(&mu_);
    active_views_.resize(workers);
  }
  for (int w = 0; w < workers; ++w) workers_.emplace_back([this, w] { WorkerLoop(w); });
}

FrameBatcher::~FrameBatcher() { Shutdown(); }

absl::Status FrameBatcher::Enqueue(FrameJob job) {
  if (job.session == nullptr || !job.done) {
    return absl::InvalidArgumentError("FrameJob: session and done are required");
  }
  const std::string& env = job.session->environment();
  if (!options_.environment.empty() && env != options_.environment) {
    return absl::InvalidArgumentError(absl::StrCat(
        "session environment '", env, "' is not this batcher's '", options_.environment, "'"));
  }
  auto item = std::make_unique<Item>();
  absl::Status status;
  int depth = 0;
  {
    absl::MutexLock lock(&mu_);
    if (stopping_) {
      status = absl::UnavailableError("frame batcher is shutting down");
    } else if (static_cast<int>(queue_.size()) >= options_.max_queue_size) {
      status = absl::ResourceExhaustedError(absl::StrCat("queue full (", options_.max_queue_size,
                                                         " frames queued for '",
                                                         options_.environment, "')"));
    } else {
      // Under mu_ so that the capacity check and the claim are atomic.
      status = job.session->TryBeginFrame(job.frame_index, std::move(job.reseed));
    }
    if (status.ok()) {
      item->job = std::move(job);
      item->enqueued = absl::Now();
      queue_.push_back(std::move(item));
      depth = static_cast<int>(queue_.size());
    }
  }
  if (!status.ok()) {
    observer_->OnRejected(options_.environment, status.code());
    return status;
  }
  observer_->OnQueueDepth(options_.environment, depth);
  return absl::OkStatus();
}

bool FrameBatcher::Cancel(const std::string& session_id) {
  bool found = false;
  int depth = -1;
  {
    absl::MutexLock lock(&mu_);
    found = CancelLocked(session_id);
    if (found) depth = static_cast<int>(queue_.size());
  }
  if (depth >= 0) observer_->OnQueueDepth(options_.environment, depth);
  return found;
}

bool FrameBatcher::CancelLocked(const std::string& session_id) {
  bool found = false;
  for (auto it = queue_.begin(); it != queue_.end();) {
    if ((*it)->job.session->id() == session_id) {
      cancelled_.push_back(std::move(*it));
      it = queue_.erase(it);
      found = true;
    } else {
      ++it;
    }
  }
  for (const std::vector<Item*>& view : active_views_) {
    for (Item* item : view) {
      if (item->job.session->id() == session_id) {
        item->cancelled.store(true);
        found = true;
      }
    }
  }
  return found;
}

void FrameBatcher::Shutdown() {
  {
    absl::MutexLock lock(&mu_);
    stopping_ = true;
  }
  absl::MutexLock join_lock(&join_mu_);
  for (std::thread& worker : workers_) {
    if (worker.joinable()) worker.join();
  }
}

int FrameBatcher::queue_depth() const {
  absl::MutexLock lock(&mu_);
  return static_cast<int>(queue_.size());
}

bool FrameBatcher::AwaitIdleWorkers(int n, absl::Duration timeout) const {
  absl::MutexLock lock(&mu_);
  auto enough = [this, n]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_) { return idle_workers_ >= n; };
  return mu_.AwaitWithTimeout(absl::Condition(&enough), timeout);
}

bool FrameBatcher::HasWork() const { return !queue_.empty() || !cancelled_.empty() || stopping_; }

bool FrameBatcher::BatchFull() const {
  // Enough for a full batch on every idle worker.
  return static_cast<int>(queue_.size()) >= worker_batch_size_ * std::max(1, idle_workers_) ||
         stopping_ || (left_for_idle_ > 0 && !queue_.empty());
}

bool FrameBatcher::ShouldDrop(const Item& item) const {
  if (item.cancelled.load()) return true;
  const std::optional<EndReason> ended = item.job.session->end_reason();
  // A draining server still answers the frames it accepted.
  return ended.has_value() && *ended != EndReason::kDraining;
}

void FrameBatcher::Fail(Item& item, absl::Status status) {
  // The frame is in flight (Enqueue claimed it), so this only fails if the
  // bookkeeping is broken; the callback still reports the frame's error.
  item.job.session->AbortFrame(item.job.frame_index).IgnoreError();
  item.timings.total_ms = Ms(absl::Now() - item.enqueued);
  observer_->OnFrameDone(options_.environment, status.code(), item.timings);
  FrameCallback done = std::move(item.job.done);
  done(std::move(status));
}

void FrameBatcher::WorkerLoop(int worker) {
  // Every LibTorch call of this worker's batches happens on this thread.
  c10::InferenceMode inference_mode;
  if (options_.threads_per_worker > 0) at::set_num_threads(options_.threads_per_worker);
  std::vector<std::unique_ptr<Item>> active;  // the running batch
  while (true) {
    std::vector<std::unique_ptr<Item>> admitted;
    std::vector<std::unique_ptr<Item>> cancelled;
    int depth = -1;
    {
      absl::MutexLock lock(&mu_);
      int admit_limit = worker_batch_size_;
      if (active.empty()) {
        ++idle_workers_;
        mu_.Await(absl::Condition(this, &FrameBatcher::HasWork));
        if (queue_.empty() && cancelled_.empty() && stopping_) {
          --idle_workers_;
          break;
        }
        if (!queue_.empty()) {
          // Let the batch fill, at most max_queue_delay after its oldest frame.
          mu_.AwaitWithDeadline(absl::Condition(this, &FrameBatcher::BatchFull),
                                queue_.front()->enqueued + options_.max_queue_delay);
        }
        // The idle workers split the queue (each at most a full batch), so
        // frames of different sessions run side by side on several workers.
        const int queued = static_cast<int>(queue_.size());
        admit_limit = std::min(admit_limit, (queued + idle_workers_ - 1) / idle_workers_);
        --idle_workers_;
      } else if (options_.mode == BatchingMode::kStepLevel && idle_workers_ > 0) {
        // A step boundary while another worker waits with no batch: it takes
        // the queued frames, now, and this batch keeps its size.
        admit_limit = 0;
        left_for_idle_ = static_cast<int>(queue_.size());
      }
      cancelled.swap(cancelled_);
      if (options_.mode == BatchingMode::kStepLevel || active.empty()) {
        while (!queue_.empty() && static_cast<int>(admitted.size()) < admit_limit &&
               static_cast<int>(active.size() + admitted.size()) < worker_batch_size_) {
          // In the view at once, so Cancel finds it while it begins.
          active_views_[worker].push_back(queue_.front().get());
          admitted.push_back(std::move(queue_.front()));
          queue_.pop_front();
        }
        if (!admitted.empty()) {
          depth = static_cast<int>(queue_.size());
          left_for_idle_ = std::max(0, left_for_idle_ - static_cast<int>(admitted.size()));
          // Took a share only: the rest is for the other idle workers.
          if (admit_limit < worker_batch_size_ && idle_workers_ > 0) left_for_idle_ = depth;
        }
      }
    }
    if (depth >= 0) observer_->OnQueueDepth(options_.environment, depth);
    for (auto& item : cancelled) Fail(*item, absl::CancelledError("frame cancelled"));
    if (!admitted.empty()) BeginItems(worker, std::move(admitted), active);
    if (!active.empty()) StepAndFinish(worker, active);
  }
}

void FrameBatcher::BeginItems(int worker, std::vector<std::unique_ptr<Item>> items,
                              std::vector<std::unique_ptr<Item>>& active) {
  const absl::Time now = absl::Now();
  std::vector<std::unique_ptr<Item>> ready;
  std::vector<model::PipelineInput> requests;
  for (auto& item : items) {
    item->timings.queue_ms = Ms(now - item->enqueued);
    if (ShouldDrop(*item)) {
      Fail(*item, absl::CancelledError("frame cancelled"));
      continue;
    }
    Session& session = *item->job.session;
    absl::StatusOr<model::PipelineInput> request;
    const absl::Status read =
        session.ReadFrameContext(item->job.frame_index, [&](FrameContext context) {
          // Only this batcher's own latent is taken; otherwise (reuse off,
          // or made before a reload) the previous frame is encoded.
          if (!options_.reuse_previous_latent || context.previous_latent.source != latent_source_) {
            context.previous_latent = LatentBuffer();
          }
          request = BuildPipelineInput(session.settings(), context, item->job.gbuffer);
        });
    absl::StatusOr<ImageBuffer> basecolor =
        BasecolorBuffer(session.settings(), item->job.gbuffer.basecolor);
    absl::Status status = read;
    if (status.ok()) status = request.status();
    if (status.ok()) status = basecolor.status();
    if (!status.ok()) {
      Fail(*item, std::move(status));
      continue;
    }
    item->basecolor = *std::move(basecolor);
    requests.push_back(*std::move(request));
    ready.push_back(std::move(item));
  }
  if (ready.empty()) return;

  std::vector<absl::Status> errors(ready.size());
  absl::StatusOr<std::vector<model::FrameState>> states = pipeline_->Begin(requests);
  if (states.ok()) {
    for (size_t i = 0; i < ready.size(); ++i) ready[i]->state = std::move((*states)[i]);
  } else if (ready.size() == 1) {
    errors[0] = states.status();
  } else {
    // One frame's bad input must not fail the others: begin them one by one.
    for (size_t i = 0; i < ready.size(); ++i) {
      absl::StatusOr<std::vector<model::FrameState>> one =
          pipeline_->Begin(absl::MakeConstSpan(&requests[i], 1));
      if (one.ok()) {
        ready[i]->state = std::move(one->front());
      } else {
        errors[i] = one.status();
      }
    }
  }
  for (size_t i = 0; i < ready.size(); ++i) {
    if (ready[i]->state.has_value()) {
      active.push_back(std::move(ready[i]));
    } else {
      Fail(*ready[i], errors[i]);
    }
  }
  // Rebuilt while the failed items are still alive (Cancel reads the view).
  absl::MutexLock lock(&mu_);
  active_views_[worker].clear();
  for (auto& item : active) active_views_[worker].push_back(item.get());
}

void FrameBatcher::StepAndFinish(int worker, std::vector<std::unique_ptr<Item>>& active) {
  // Step boundary: drop cancelled frames first.
  std::vector<std::unique_ptr<Item>> dropped;
  for (auto& item : active) {
    if (ShouldDrop(*item)) dropped.push_back(std::move(item));
  }
  active.erase(std::remove(active.begin(), active.end(), nullptr), active.end());

  std::vector<model::FrameState*> stepping;
  for (auto& item : active) {
    if (!item->state->finished()) stepping.push_back(&*item->state);
  }
  absl::Status step_status = absl::OkStatus();
  if (!stepping.empty()) {
    const int n = static_cast<int>(stepping.size());
    for (auto& item : active) {
      if (!item->state->finished())
        item->timings.batch_size = std::max(item->timings.batch_size, n);
    }
    observer_->OnStepBatch(options_.environment, n);
    step_status = pipeline_->Step(stepping);
  }

  std::vector<std::unique_ptr<Item>> failed;
  std::vector<std::unique_ptr<Item>> finished;
  for (auto& item : active) {
    if (!step_status.ok()) {
      failed.push_back(std::move(item));
    } else if (item->state->finished()) {
      finished.push_back(std::move(item));
    }
  }
  active.erase(std::remove(active.begin(), active.end(), nullptr), active.end());
  {
    absl::MutexLock lock(&mu_);
    active_views_[worker].clear();
    for (auto& item : active) active_views_[worker].push_back(item.get());
  }

  for (auto& item : dropped) Fail(*item, absl::CancelledError("frame cancelled"));
  for (auto& item : failed) Fail(*item, step_status);
  if (finished.empty()) return;

  std::vector<model::FrameState*> states;
  for (auto& item : finished) states.push_back(&*item->state);
  absl::StatusOr<std::vector<model::FrameOutput>> outputs = pipeline_->Finish(states);
  for (size_t i = 0; i < finished.size(); ++i) {
    Item& item = *finished[i];
    if (!outputs.ok()) {
      Fail(item, outputs.status());
      continue;
    }
    const model::FrameOutput& output = (*outputs)[i];
    Session& session = *item.job.session;
    // The output buffer shares the tensor's storage; the session keeps it as
    // its previous frame and the stream encodes the same bytes.
    absl::StatusOr<ImageBuffer> image = OutputImage(session.settings(), output.image_uint8);
    absl::Status status = image.status();
    absl::StatusOr<ImageBuffer> image_float = ImageBuffer();
    if (status.ok() && output.image_float.defined()) {
      image_float = OutputFloatImage(session.settings(), output.image_float);
      status = image_float.status();
    }
    absl::StatusOr<LatentBuffer> latent = LatentBuffer();
    if (status.ok() && options_.reuse_previous_latent) {
      latent = OutputLatent(output.latent);
      status = latent.status();
      if (latent.ok()) latent->source = latent_source_;
    }
    if (status.ok()) {
      status = session.CommitFrame(item.job.frame_index, *image, std::move(item.basecolor),
                                   *std::move(latent));
    }
    if (!status.ok()) {
      Fail(item, std::move(status));
      continue;
    }
    item.state.reset();  // free the tensors before the callback
    item.timings.encode_ms = output.timings.encode_ms;
    item.timings.denoise_ms = output.timings.denoise_ms;
    item.timings.decode_ms = output.timings.decode_ms;
    item.timings.total_ms = Ms(absl::Now() - item.enqueued);
    observer_->OnFrameDone(options_.environment, absl::StatusCode::kOk, item.timings);
    FrameResult result;
    result.frame_index = item.job.frame_index;
    result.width = session.settings().width;
    result.height = session.settings().height;
    result.image = *std::move(image);
    result.image_float = *std::move(image_float);
    result.timings = item.timings;
    FrameCallback done = std::move(item.job.done);
    done(std::move(result));
  }
}

}  // namespace fd::session

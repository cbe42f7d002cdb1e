// FrameBatcher: one per environment. A worker thread owns the
// environment's pipeline and makes every model call (under
// torch::InferenceMode); frames of many sessions are batched into one
// network call per denoising step (Triton's "sequence batcher with implicit
// state", natively: the implicit state is the Session).
//
// Per-session order: a session has at most one frame in flight
// (Session::TryBeginFrame at Enqueue), so its frames run in order and each
// sees the previous one's committed output.
//
// Batching modes:
//  * kWholeFrame: the worker takes up to max_batch_size queued frames
//    (waiting at most max_queue_delay after the oldest for the batch to
//    fill), runs Begin, every step and Finish for that batch, and only then
//    takes the next batch.
//  * kStepLevel: the same, except that at every denoising-step boundary
//    frames queued meanwhile join the running batch (Begin, up to
//    max_batch_size in all), and each frame is Finish()ed and delivered as
//    soon as its own last step ran, without waiting for the others (every
//    item carries its own solver state, model::FrameState).
// A frame's noise depends only on (session seed, frame counter), so a
// session renders the same frames alone, in any batch, and in either mode.
//
// Cancellation (Cancel(session id), or the session ended for a reason other
// than draining): a queued frame is dropped; an in-flight frame is DROPPED
// AT THE NEXT STEP BOUNDARY (it does not finish). Either way the session's
// state is not advanced (AbortFrame) and the callback gets CANCELLED.
//
// Failures: if a model call fails, every frame in that call gets the error,
// its session is AbortFrame()d (state not advanced, the client may retry the
// same frame index with the same noise) and stays usable. A frame whose own
// inputs are invalid fails alone (Begin is retried per frame).
#ifndef FD_SESSION_FRAME_BATCHER_H_
#define FD_SESSION_FRAME_BATCHER_H_

#include <cstdint>
#include <deque>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "session/batcher_observer.h"
#include "session/frame_job.h"
#include "session/frame_pipeline_interface.h"
#include "session/frame_queue.h"
#include "session/pipeline_input_builder.h"
#include "session/session.h"

namespace fd::session {

enum class BatchingMode {
  kWholeFrame,
  kStepLevel,
};

struct FrameBatcherOptions {
  // The environment's name: Enqueue refuses sessions of other environments
  // (empty: no check) and metrics are labelled with it.
  std::string environment;
  BatchingMode mode = BatchingMode::kStepLevel;
  // Most frames denoised together (>= 1), over all workers: each worker's
  // batch holds at most ceil(max_batch_size / workers) frames.
  int max_batch_size = 8;
  // How long an idle worker waits after the oldest queued frame for a batch
  // to fill before starting a smaller one. Not applied when frames join a
  // running batch (kStepLevel) or while draining. With several workers, the
  // idle ones wait for a full batch each, then split the queue; an infinite
  // delay can then hold the last frames of a run until more arrive.
  absl::Duration max_queue_delay = absl::Milliseconds(2);
  // Most frames queued (not yet in a batch); Enqueue answers
  // RESOURCE_EXHAUSTED beyond it.
  int max_queue_size = 64;
  // Worker threads (>= 1), each running its own batch on the shared queue.
  // On a CPU where the model's kernels are too small to use several cores
  // well (the tiny preset: one LibTorch thread renders a 64x64 frame twice
  // as fast as two), two workers of one thread each render two batches at
  // once. Each worker's batch is capped at its share of max_batch_size, so
  // sessions spread over the workers. A session is on one worker at a time
  // (it has one frame in flight), so per-session order holds.
  int workers = 1;
  // LibTorch intra-op threads of each worker (at::set_num_threads on the
  // worker thread; OpenMP keeps the setting per thread). 0: leave the
  // process default.
  int threads_per_worker = 0;
  // The environment's "previous_latent": "reuse": each frame's denoised
  // latent is committed with its output, and the session's next frame takes
  // it instead of the VAE encode of that output (session_state.h).
  bool reuse_previous_latent = false;
};

// Ownership: owns its pipeline and worker threads; borrows the observer
// (which must outlive it). Thread-safety: every public method may be called
// from any thread, including from a FrameCallback (except Shutdown and the
// destructor, which join the worker).
class FrameBatcher final : public FrameQueue {
 public:
  FrameBatcher(std::unique_ptr<FramePipelineInterface> pipeline, FrameBatcherOptions options,
               FrameBatcherObserver* observer = NoopFrameBatcherObserver::Get());
  // Shutdown().
  ~FrameBatcher();

  FrameBatcher(const FrameBatcher&) = delete;
  FrameBatcher& operator=(const FrameBatcher&) = delete;

  // Queues one frame; never blocks on the model. On OK the frame is in
  // flight for its session and `job.done` will be called exactly once.
  // Errors (job.done is then not called): INVALID_ARGUMENT (no session or
  // callback, a session of another environment, or from
  // Session::TryBeginFrame), RESOURCE_EXHAUSTED "queue full",
  // UNAVAILABLE after Shutdown began, FAILED_PRECONDITION from
  // Session::TryBeginFrame (a frame already in flight, a frame index not
  // increasing, an ended session).
  absl::Status Enqueue(FrameJob job) override ABSL_LOCKS_EXCLUDED(mu_);

  // Cancels the session's frame: dropped if queued, dropped at the next step
  // boundary if in flight (callback CANCELLED, state unchanged). Frames
  // enqueued after this call are not affected. Returns whether a frame was
  // found.
  bool Cancel(const std::string& session_id) override ABSL_LOCKS_EXCLUDED(mu_);

  // Stops accepting frames (Enqueue: UNAVAILABLE), renders every queued and
  // in-flight frame, and joins the worker. Idempotent. Must not be called
  // from a FrameCallback.
  void Shutdown() override ABSL_LOCKS_EXCLUDED(mu_);

  // Frames queued, not yet in a batch.
  int queue_depth() const ABSL_LOCKS_EXCLUDED(mu_);

  // Blocks until `n` workers wait for frames with no batch running (at most
  // `timeout`); returns whether they do. For tests that need every worker
  // ready before frames arrive, and for start-up checks.
  bool AwaitIdleWorkers(int n, absl::Duration timeout) const ABSL_LOCKS_EXCLUDED(mu_);

 private:
  struct Item;

  bool CancelLocked(const std::string& session_id) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  void WorkerLoop(int worker);
  bool HasWork() const ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  bool BatchFull() const ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // Begins `items` (one Begin call; per item on failure); the ones that
  // started are appended to `active`, the others delivered with an error.
  void BeginItems(int worker, std::vector<std::unique_ptr<Item>> items,
                  std::vector<std::unique_ptr<Item>>& active);
  // Runs one step for `active`, then finishes and delivers the finished.
  void StepAndFinish(int worker, std::vector<std::unique_ptr<Item>>& active);
  // Aborts the item's frame and calls its callback with `status`.
  void Fail(Item& item, absl::Status status);
  bool ShouldDrop(const Item& item) const;

  const std::unique_ptr<FramePipelineInterface> pipeline_;
  const FrameBatcherOptions options_;
  // Tags the latents this batcher commits (LatentBuffer::source): unique per
  // batcher in the process, so a latent kept from before a reload (another
  // batcher, maybe another autoencoder) is never taken.
  const uint64_t latent_source_;
  FrameBatcherObserver* const observer_;
  // ceil(max_batch_size / workers): one worker's batch cap. Idle workers wait
  // (up to max_queue_delay) for a full batch each, then split the queue.
  const int worker_batch_size_;

  mutable absl::Mutex mu_;
  bool stopping_ ABSL_GUARDED_BY(mu_) = false;
  std::deque<std::unique_ptr<Item>> queue_ ABSL_GUARDED_BY(mu_);
  // Queued frames removed by Cancel, to be delivered by the worker.
  std::vector<std::unique_ptr<Item>> cancelled_ ABSL_GUARDED_BY(mu_);
  // Per worker: the items of its running batch (owned by the worker), for
  // Cancel.
  std::vector<std::vector<Item*>> active_views_ ABSL_GUARDED_BY(mu_);
  // Workers with no running batch, waiting for frames. Queued frames are
  // shared among them, and a busy worker admits no frame at a step boundary
  // while one of them waits, so 2 sessions on 2 workers run side by side
  // instead of as one batch of 2 on one core.
  int idle_workers_ ABSL_GUARDED_BY(mu_) = 0;
  // Frames a worker left queued for the other idle workers when it took its
  // share: they start them without waiting for a full batch.
  int left_for_idle_ ABSL_GUARDED_BY(mu_) = 0;

  absl::Mutex join_mu_;  // serialises Shutdown's join
  std::vector<std::thread> workers_;
};

}  // namespace fd::session

#endif  // FD_SESSION_FRAME_BATCHER_H_

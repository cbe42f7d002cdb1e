// What the frame batcher reports to metrics. The server implements this
// interface (prometheus histograms/gauges); session/ must not depend on
// prometheus or gRPC.
#ifndef FD_SESSION_BATCHER_OBSERVER_H_
#define FD_SESSION_BATCHER_OBSERVER_H_

#include <string_view>

#include "absl/status/status.h"

namespace fd::session {

// Per-frame timings in milliseconds, measured by the batcher (queue,
// total) and the pipeline (encode, denoise, decode).
struct FrameTimings {
  double queue_ms = 0;    // Enqueue -> the frame joined a batch (Begin)
  double encode_ms = 0;   // conditioning + VAE encode + noise (Begin)
  double denoise_ms = 0;  // the batched denoising steps this frame took part in
  double decode_ms = 0;   // VAE decode + postprocess (Finish)
  double total_ms = 0;    // Enqueue -> just before the callback
  int batch_size = 0;     // most frames denoised together with this one (itself included)
};

// Ownership: the batcher borrows it; it must outlive the batcher.
// Thread-safety: called from the batcher's worker thread and (OnRejected,
// OnQueueDepth) from threads calling Enqueue, concurrently, never with a
// session lock held. Implementations should be cheap and must not block.
class FrameBatcherObserver {
 public:
  virtual ~FrameBatcherObserver() = default;
  // The number of queued frames (not yet in a batch) changed.
  virtual void OnQueueDepth(std::string_view environment, int depth) {}
  // One denoising step ran for `batch_size` frames together.
  virtual void OnStepBatch(std::string_view environment, int batch_size) {}
  // A frame ended: OK (timings all set), CANCELLED, or the batch's error
  // (timings partly set).
  virtual void OnFrameDone(std::string_view environment, absl::StatusCode code,
                           const FrameTimings& timings) {}
  // Enqueue refused a frame (RESOURCE_EXHAUSTED queue full, UNAVAILABLE
  // shutting down, FAILED_PRECONDITION from the session).
  virtual void OnRejected(std::string_view environment, absl::StatusCode code) {}
};

// Does nothing: the default when the server passes no observer.
class NoopFrameBatcherObserver final : public FrameBatcherObserver {
 public:
  static FrameBatcherObserver* Get() {
    static NoopFrameBatcherObserver* const observer = new NoopFrameBatcherObserver();
    return observer;
  }
};

}  // namespace fd::session

#endif  // FD_SESSION_BATCHER_OBSERVER_H_

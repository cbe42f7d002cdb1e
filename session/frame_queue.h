// FrameQueue: what a stream needs from an environment's frame batcher:
// enqueue a frame, cancel a session's frames, stop. The server's stream
// controller uses the batcher only through this (FrameBatcher implements
// it), so it does not depend on how frames are batched.
#ifndef FD_SESSION_FRAME_QUEUE_H_
#define FD_SESSION_FRAME_QUEUE_H_

#include <string>

#include "absl/status/status.h"
#include "session/frame_job.h"

namespace fd::session {

// Thread-safety: implementations are thread-safe; Enqueue and Cancel may be
// called from a frame's callback.
class FrameQueue {
 public:
  virtual ~FrameQueue() = default;

  // Queues `job`; its callback runs exactly once. RESOURCE_EXHAUSTED when
  // the queue is full, UNAVAILABLE after Shutdown, FAILED_PRECONDITION when
  // the session has a frame in flight or the frame_index is not newer,
  // INVALID_ARGUMENT for a session of another environment.
  virtual absl::Status Enqueue(FrameJob job) = 0;
  // Drops the session's queued frame and cancels its in-flight one at the
  // next step boundary (callbacks get CANCELLED). True if it had one.
  virtual bool Cancel(const std::string& session_id) = 0;
  // Renders what was accepted, then refuses new frames (UNAVAILABLE).
  virtual void Shutdown() = 0;
};

}  // namespace fd::session

#endif  // FD_SESSION_FRAME_QUEUE_H_

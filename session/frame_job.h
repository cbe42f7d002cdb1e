// One frame handed to a FrameQueue (frame_queue.h) and what comes back.
#ifndef FD_SESSION_FRAME_JOB_H_
#define FD_SESSION_FRAME_JOB_H_

#include <cstdint>
#include <functional>
#include <memory>
#include <optional>

#include "absl/status/statusor.h"
#include "base/image_buffer.h"
#include "session/batcher_observer.h"
#include "session/pipeline_input_builder.h"
#include "session/session.h"

namespace fd::session {

// A rendered frame.
struct FrameResult {
  uint64_t frame_index = 0;
  uint32_t width = 0;
  uint32_t height = 0;
  // uint8 HWC RGB, width x height x 3: the same buffer the session keeps as
  // its previous frame (shared, immutable; not copied).
  ImageBuffer image;
  // The same frame before quantisation, float32 HWC RGB in [0, 1]; only
  // when the session's output_dtype is not kUint8 (the state always keeps
  // the uint8 frame, as the reference does); empty otherwise.
  ImageBuffer image_float;
  FrameTimings timings;
};

// Called exactly once per accepted frame, ON THE WORKER THREAD: it must not
// block (hand the result to another thread, or Enqueue the session's next
// frame, which never blocks). OK: the session's state was already committed
// (previous frame <- image, previous basecolor <- this frame's basecolor,
// counter + 1). An error (CANCELLED, the batch's error): the frame was
// aborted, the state did not change.
using FrameCallback = std::function<void(absl::StatusOr<FrameResult>)>;

// One frame to render.
struct FrameJob {
  std::shared_ptr<Session> session;
  uint64_t frame_index = 0;
  std::optional<Keyframe> reseed;  // camera cut: re-seed the chain
  FrameGBuffer gbuffer;            // shared images; the batcher keeps them until the callback
  FrameCallback done;
};

}  // namespace fd::session

#endif  // FD_SESSION_FRAME_JOB_H_

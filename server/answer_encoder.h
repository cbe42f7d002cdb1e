// AnswerEncoder: one background thread that turns rendered frames into wire
// answers (EncodeImage: fp16 conversion, zstd, the copy into the proto), so
// that the batcher's worker thread, which the next batch waits for, only
// hands the result over and goes on.
//
// Tasks run one at a time in the order they were posted, so a stream's
// answers are encoded in its frames' order. Ownership: owned by
// RenderService; the destructor runs what is queued, then joins.
// Thread-safety: Post may be called from any thread, including a task.
#ifndef FD_SERVER_ANSWER_ENCODER_H_
#define FD_SERVER_ANSWER_ENCODER_H_

#include <deque>
#include <functional>
#include <thread>

#include "absl/base/thread_annotations.h"
#include "absl/synchronization/mutex.h"

namespace fd::server {

class AnswerEncoder {
 public:
  AnswerEncoder();
  ~AnswerEncoder();

  AnswerEncoder(const AnswerEncoder&) = delete;
  AnswerEncoder& operator=(const AnswerEncoder&) = delete;

  // Runs `task` on the encoder thread after the tasks posted before it.
  void Post(std::function<void()> task) ABSL_LOCKS_EXCLUDED(mu_);

 private:
  void Loop() ABSL_LOCKS_EXCLUDED(mu_);

  absl::Mutex mu_;
  std::deque<std::function<void()>> tasks_ ABSL_GUARDED_BY(mu_);
  bool stopping_ ABSL_GUARDED_BY(mu_) = false;
  std::thread thread_;
};

}  // namespace fd::server

#endif  // FD_SERVER_ANSWER_ENCODER_H_

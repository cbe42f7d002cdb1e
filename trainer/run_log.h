// What a training run tells its user: a progress line (stage, step, loss
// EMA, steps/s, ETA) on stderr, a JSONL log of every logged step and event
// (train/log.jsonl, appended across --resume), and per-stage loss curves
// (train/loss-<stage>.png, fd::client_io's plot).
//
// Thread-safety: one thread (the training loop).
#ifndef FD_TRAINER_RUN_LOG_H_
#define FD_TRAINER_RUN_LOG_H_

#include <array>
#include <cstdint>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "trainer/sample_builder.h"

namespace fd::trainer {

struct StepRecord {
  Stage stage = Stage::kVae;
  int64_t step = 0;   // optimizer steps done in the stage
  int64_t total = 0;  // the stage's steps
  double loss = 0;
  double lr = 0;
  double step_seconds = 0;   // wall time of this step
  double wait_fraction = 0;  // of the stage's step time, waiting for batches
};

class RunLog {
 public:
  // Opens (appends to) `train_dir`/log.jsonl, reading the loss history a
  // previous run left there. INTERNAL when the folder cannot be written.
  static absl::StatusOr<std::unique_ptr<RunLog>> Open(const std::string& train_dir,
                                                      bool progress_bar, int64_t log_every);

  // Every optimizer step: updates the loss EMA and the progress line; every
  // log_every steps (and the last) appends a JSONL record.
  void Step(const StepRecord& record);
  // A one-line event (stage start/end, validation, checkpoint): JSONL, and a
  // human line on stderr.
  void Event(const std::string& what, const nlohmann::json& fields);
  // train/loss-<stage>.png of the logged EMA. INTERNAL / INVALID_ARGUMENT
  // from the PNG writer or plot (none logged yet: OK, nothing written).
  absl::Status WriteLossCurve(Stage stage) const;

  double loss_ema() const { return ema_; }
  const std::string& dir() const { return dir_; }

 private:
  RunLog(std::string dir, bool progress_bar, int64_t log_every);
  void Append(const nlohmann::json& record);

  std::string dir_;
  bool progress_bar_;
  int64_t log_every_;
  double ema_ = 0;
  int64_t ema_count_ = 0;
  double rate_ = 0;  // steps/s (EMA)
  bool line_open_ = false;
  std::array<std::vector<int64_t>, kStageCount> curve_steps_;
  std::array<std::vector<double>, kStageCount> curve_loss_;
};

}  // namespace fd::trainer

#endif  // FD_TRAINER_RUN_LOG_H_

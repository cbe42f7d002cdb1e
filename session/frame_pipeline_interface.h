// What the frame batcher needs from a model pipeline: the step-level
// batching entry points of model::FramePipeline. An interface so that tests
// can wrap the real pipeline to inject failures or pause a step
// (tests/testing/scripted_frame_pipeline.h); production uses
// ModelFramePipeline.
#ifndef FD_SESSION_FRAME_PIPELINE_INTERFACE_H_
#define FD_SESSION_FRAME_PIPELINE_INTERFACE_H_

#include <memory>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/types/span.h"
#include "model/pipeline/frame_pipeline.h"

namespace fd::session {

// Same contracts (arguments, status codes) as model::FramePipeline's Begin,
// Step and Finish. Thread-safety: the scheduler calls it from its worker
// thread only.
class FramePipelineInterface {
 public:
  virtual ~FramePipelineInterface() = default;
  virtual absl::StatusOr<std::vector<model::FrameState>> Begin(
      absl::Span<const model::PipelineInput> items) const = 0;
  virtual absl::Status Step(absl::Span<model::FrameState* const> states) const = 0;
  virtual absl::StatusOr<std::vector<model::FrameOutput>> Finish(
      absl::Span<model::FrameState* const> states) const = 0;
};

// The real pipeline. Ownership: owns its model::FramePipeline (which shares
// the environment).
class ModelFramePipeline final : public FramePipelineInterface {
 public:
  explicit ModelFramePipeline(std::shared_ptr<const model::Environment> environment,
                              model::FramePipelineOptions options = {})
      : pipeline_(std::move(environment), options) {}

  absl::StatusOr<std::vector<model::FrameState>> Begin(
      absl::Span<const model::PipelineInput> items) const override {
    return pipeline_.Begin(items);
  }
  absl::Status Step(absl::Span<model::FrameState* const> states) const override {
    return pipeline_.Step(states);
  }
  absl::StatusOr<std::vector<model::FrameOutput>> Finish(
      absl::Span<model::FrameState* const> states) const override {
    return pipeline_.Finish(states);
  }

 private:
  model::FramePipeline pipeline_;
};

}  // namespace fd::session

#endif  // FD_SESSION_FRAME_PIPELINE_INTERFACE_H_

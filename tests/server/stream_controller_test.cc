// StreamController without gRPC: a recording StreamOutput stands in for the
// reactor; the session store, the environment registry and the frame
// batcher are the real ones, on the random tiny environment.
#include "server/stream_controller.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <memory>
#include <string>
#include <vector>

#include "absl/synchronization/mutex.h"
#include "absl/synchronization/notification.h"
#include "session/clock.h"
#include "session/end_reason.h"
#include "session/environment_registry.h"
#include "session/session_store.h"
#include "tests/server/server_test_util.h"

namespace fd::server {
namespace {

using ::fd::server::testing::MakeFrame;
using ::fd::server::testing::MakeOpen;
using ::fd::server::testing::MakeResume;
using ::testing::HasSubstr;

constexpr char kEnv[] = "tiny";

// Records what the controller asks of the reactor. Writes complete only
// when the test says so (Complete), like a slow network.
class RecordingOutput : public StreamOutput {
 public:
  void Write(v1::RenderResponse response, bool frame_answer) override {
    absl::MutexLock lock(&mu_);
    writes_.push_back({std::move(response), frame_answer});
  }
  void Finish(const absl::Status& status) override {
    absl::MutexLock lock(&mu_);
    finish_ = status;
  }
  void Read() override {
    absl::MutexLock lock(&mu_);
    ++reads_;
  }

  // Waits until `n` messages were written.
  std::vector<v1::RenderResponse> AwaitWrites(size_t n) {
    absl::MutexLock lock(&mu_);
    awaited_ = n;
    mu_.Await(absl::Condition(
        +[](RecordingOutput* self)
             ABSL_NO_THREAD_SAFETY_ANALYSIS { return self->writes_.size() >= self->awaited_; },
        this));
    std::vector<v1::RenderResponse> out;
    for (const auto& w : writes_) out.push_back(w.response);
    return out;
  }
  std::optional<absl::Status> AwaitFinish() {
    absl::MutexLock lock(&mu_);
    mu_.Await(absl::Condition(
        +[](RecordingOutput* self)
             ABSL_NO_THREAD_SAFETY_ANALYSIS { return self->finish_.has_value(); },
        this));
    return finish_;
  }
  int reads() {
    absl::MutexLock lock(&mu_);
    return reads_;
  }
  bool finished() {
    absl::MutexLock lock(&mu_);
    return finish_.has_value();
  }
  // Reports every write so far as completed.
  void CompleteAll(StreamController& controller) {
    std::vector<bool> answers;
    {
      absl::MutexLock lock(&mu_);
      for (size_t i = completed_; i < writes_.size(); ++i) answers.push_back(writes_[i].frame);
      completed_ = writes_.size();
    }
    for (bool frame : answers) controller.OnWritten(frame, /*ok=*/true);
  }

 private:
  struct Written {
    v1::RenderResponse response;
    bool frame = false;
  };
  absl::Mutex mu_;
  std::vector<Written> writes_ ABSL_GUARDED_BY(mu_);
  size_t completed_ ABSL_GUARDED_BY(mu_) = 0;
  size_t awaited_ ABSL_GUARDED_BY(mu_) = 0;
  std::optional<absl::Status> finish_ ABSL_GUARDED_BY(mu_);
  int reads_ ABSL_GUARDED_BY(mu_) = 0;
};

class StreamControllerTest : public ::testing::Test {
 protected:
  void SetUp() override {
    session::SessionStoreOptions store_options;
    store_ = *session::SessionStore::Create(store_options, session::RealClock::Get());
    MakeRegistry(nullptr);
  }
  // The registry serving the tiny environment; `factory` wraps its pipeline.
  void MakeRegistry(session::PipelineFactory factory) {
    if (registry_ != nullptr) registry_->Shutdown();  // nothing rendering yet
    session::EnvironmentRegistryOptions registry_options;
    registry_options.batcher.max_queue_delay = absl::ZeroDuration();
    registry_options.pipeline_factory = std::move(factory);
    registry_ = std::make_unique<session::EnvironmentRegistry>(std::move(registry_options));
    ASSERT_TRUE(registry_->AddLoaded(kEnv, testing::TinyEnvironment()).ok());
  }
  void TearDown() override {
    gate_->Open();  // a test that failed early must not leave a frame waiting
    registry_->Shutdown();
  }

  // Frames stop at their first denoising step until gate_ opens;
  // stepping_ says that one got there.
  void GateFirstSteps() { MakeRegistry(testing::GatedFirstStep(gate_, stepping_)); }

  std::shared_ptr<StreamController> MakeController(RecordingOutput* output) {
    StreamServices services;
    services.registry = registry_.get();
    services.store = store_.get();
    services.limits.min_size = 16;
    services.limits.max_frames_in_flight = 4;
    services.server_draining = [] { return false; };
    services.session_released = [this](const std::string& id) {
      absl::MutexLock lock(&released_mu_);
      released_.push_back(id);
    };
    auto controller = std::make_shared<StreamController>(std::move(services), output, "test", "");
    controller->Start(std::string("alice"));
    return controller;
  }

  // Opens a session (max_frames_in_flight `in_flight`) and completes the
  // SessionOpened write.
  v1::SessionOpened Open(StreamController& controller, RecordingOutput& output,
                         uint32_t in_flight = 4) {
    v1::RenderRequest open = MakeOpen(kEnv);
    open.mutable_open()->set_max_frames_in_flight(in_flight);
    EXPECT_EQ(controller.OnRead(open), "");
    const std::vector<v1::RenderResponse> writes = output.AwaitWrites(1);
    EXPECT_TRUE(writes[0].has_opened());
    output.CompleteAll(controller);
    return writes[0].opened();
  }

  std::unique_ptr<session::SessionStore> store_;
  std::unique_ptr<session::EnvironmentRegistry> registry_;
  std::shared_ptr<fd::testing::Gate> gate_ = std::make_shared<fd::testing::Gate>();
  std::shared_ptr<absl::Notification> stepping_ = std::make_shared<absl::Notification>();
  absl::Mutex released_mu_;
  std::vector<std::string> released_ ABSL_GUARDED_BY(released_mu_);
};

TEST_F(StreamControllerTest, OpenGoesFromOpeningToOpen) {
  RecordingOutput output;
  auto controller = MakeController(&output);
  EXPECT_EQ(controller->phase(), StreamPhase::kOpening);
  EXPECT_EQ(output.reads(), 1);  // the first message
  const v1::SessionOpened opened = Open(*controller, output);
  EXPECT_EQ(controller->phase(), StreamPhase::kOpen);
  EXPECT_EQ(controller->session_id(), opened.session_id());
  EXPECT_GE(output.reads(), 2);  // reading frames now
  controller->Detach(/*call_cancelled=*/false);
}

TEST_F(StreamControllerTest, BadFirstMessageClosesWithTheError) {
  RecordingOutput output;
  auto controller = MakeController(&output);
  controller->OnRead(MakeFrame(0));
  const std::optional<absl::Status> finish = output.AwaitFinish();
  EXPECT_EQ(finish->code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(finish->message()), HasSubstr("must be open or resume"));
  EXPECT_EQ(controller->phase(), StreamPhase::kClosed);
}

// Answers leave in frame order even when a later frame's error is known
// first: good 5, invalid 6, good 7 answer F5 E6 F7.
TEST_F(StreamControllerTest, FrameErrorsWaitBehindEarlierFrames) {
  GateFirstSteps();
  RecordingOutput output;
  auto controller = MakeController(&output);
  Open(*controller, output);
  v1::RenderRequest invalid = MakeFrame(6);
  invalid.mutable_frame()->mutable_gbuffer()->clear_normals();
  controller->OnRead(MakeFrame(5));
  stepping_->WaitForNotification();  // frame 5 is rendering
  controller->OnRead(invalid);
  controller->OnRead(MakeFrame(7));
  EXPECT_EQ(output.AwaitWrites(1).size(), 1u);  // E6 waits behind F5
  gate_->Open();
  const std::vector<v1::RenderResponse> writes = output.AwaitWrites(4);
  ASSERT_TRUE(writes[1].has_frame()) << writes[1].DebugString();
  EXPECT_EQ(writes[1].frame().frame_index(), 5u);
  ASSERT_TRUE(writes[2].has_frame_error()) << writes[2].DebugString();
  EXPECT_EQ(writes[2].frame_error().frame_index(), 6u);
  EXPECT_THAT(writes[2].frame_error().message(), HasSubstr("frame.gbuffer.normals"));
  ASSERT_TRUE(writes[3].has_frame()) << writes[3].DebugString();
  EXPECT_EQ(writes[3].frame().frame_index(), 7u);
  controller->Detach(/*call_cancelled=*/false);
}

// The stream reads at most max_frames_in_flight frames ahead of the
// answers the network has taken.
TEST_F(StreamControllerTest, FlowControlWaitsForWrittenAnswers) {
  RecordingOutput output;
  auto controller = MakeController(&output);
  Open(*controller, output, /*in_flight=*/1);
  const int reads_before = output.reads();
  controller->OnRead(MakeFrame(0));
  output.AwaitWrites(2);  // the answer is handed over, not yet written
  EXPECT_EQ(output.reads(), reads_before);
  output.CompleteAll(*controller);
  EXPECT_EQ(output.reads(), reads_before + 1);
  controller->Detach(/*call_cancelled=*/false);
}

// A half-close closes the session once every frame is answered and the
// call completed (Detach, not cancelled); until then the close is pending.
TEST_F(StreamControllerTest, HalfCloseClosesTheSessionAfterTheAnswers) {
  RecordingOutput output;
  auto controller = MakeController(&output);
  const v1::SessionOpened opened = Open(*controller, output);
  controller->OnRead(MakeFrame(0));
  controller->OnReadFailed(/*cancelled=*/false);
  const std::optional<absl::Status> finish = output.AwaitFinish();
  EXPECT_TRUE(finish->ok()) << *finish;
  const std::vector<v1::RenderResponse> writes = output.AwaitWrites(2);
  EXPECT_TRUE(writes[1].has_frame());
  EXPECT_EQ(controller->phase(), StreamPhase::kClosed);
  absl::StatusOr<std::shared_ptr<session::Session>> live = store_->Lookup(opened.session_id());
  ASSERT_TRUE(live.ok()) << live.status();
  EXPECT_TRUE((*live)->close_pending());
  controller->Detach(/*call_cancelled=*/false);
  EXPECT_FALSE((*live)->close_pending());
  const absl::Status resumed =
      store_->Resume(opened.session_id(), opened.resume_token(), "alice").status();
  EXPECT_EQ(resumed.code(), absl::StatusCode::kNotFound) << resumed;
  EXPECT_EQ(session::EndReasonFromStatus(resumed), session::EndReason::kClosed);
  absl::MutexLock lock(&released_mu_);
  EXPECT_THAT(released_, ::testing::ElementsAre(opened.session_id()));
}

// Issue 19, defect 3: gRPC fails a read on a broken call (e.g. a message
// above its own size limit) before it marks the call cancelled, so the
// controller first takes it for a half-close. The call's end decides: it
// was cancelled, so the session stays open and resumable.
TEST_F(StreamControllerTest, HalfCloseOfABrokenCallKeepsTheSession) {
  RecordingOutput output;
  auto controller = MakeController(&output);
  const v1::SessionOpened opened = Open(*controller, output);
  controller->OnReadFailed(/*cancelled=*/false);
  EXPECT_TRUE(output.AwaitFinish()->ok());
  controller->OnCancel();
  controller->Detach(/*call_cancelled=*/true);
  absl::StatusOr<std::shared_ptr<session::Session>> resumed =
      store_->Resume(opened.session_id(), opened.resume_token(), "alice");
  ASSERT_TRUE(resumed.ok()) << resumed.status();
  EXPECT_FALSE((*resumed)->close_pending());
  EXPECT_FALSE((*resumed)->end_reason().has_value());
}

// A resume that arrives while a half-close's close is pending waits for the
// outcome: the close completed -> notice CLOSED and NOT_FOUND; the call
// broke -> resumed.
TEST_F(StreamControllerTest, AResumeWaitsForAPendingClose) {
  for (const bool call_cancelled : {false, true}) {
    SCOPED_TRACE(call_cancelled ? "call broke" : "call completed");
    RecordingOutput first_output;
    auto first = MakeController(&first_output);
    const v1::SessionOpened opened = Open(*first, first_output);
    first->OnReadFailed(/*cancelled=*/false);
    EXPECT_TRUE(first_output.AwaitFinish()->ok());

    RecordingOutput output;
    auto second = MakeController(&output);
    EXPECT_EQ(second->OnRead(MakeResume(opened.session_id(), opened.resume_token())),
              opened.session_id());
    second->OnSessionReleased();                         // what the service's TakeOver does
    EXPECT_EQ(second->phase(), StreamPhase::kResuming);  // held: the close is pending
    EXPECT_FALSE(output.finished());

    first->Detach(call_cancelled);
    {
      absl::MutexLock lock(&released_mu_);
      ASSERT_FALSE(released_.empty());
      EXPECT_EQ(released_.back(), opened.session_id());
    }
    second->OnSessionReleased();  // what the service's SessionReleased does
    const std::vector<v1::RenderResponse> writes = output.AwaitWrites(1);
    if (call_cancelled) {
      ASSERT_TRUE(writes[0].has_opened()) << writes[0].DebugString();
      EXPECT_TRUE(writes[0].opened().resumed());
      EXPECT_EQ(second->phase(), StreamPhase::kOpen);
      EXPECT_FALSE(output.finished());
    } else {
      ASSERT_TRUE(writes[0].has_notice()) << writes[0].DebugString();
      EXPECT_EQ(writes[0].notice().reason(), v1::SessionNotice::REASON_CLOSED);
      const std::optional<absl::Status> finish = output.AwaitFinish();
      EXPECT_EQ(finish->code(), absl::StatusCode::kNotFound) << *finish;
      EXPECT_THAT(std::string(finish->message()), HasSubstr("resume: "));
    }
    second->Detach(/*call_cancelled=*/false);
  }
}

// A message that is too large or does not parse ends the stream with an
// error naming its size; the session stays resumable (not a half-close).
TEST_F(StreamControllerTest, UnreadableMessagesKeepTheSession) {
  struct Case {
    StreamController::Unreadable why;
    absl::StatusCode code;
    std::string message;
  };
  for (const Case& c :
       {Case{StreamController::Unreadable::kUnparsable, absl::StatusCode::kInvalidArgument,
             "request: 4321 bytes that do not parse as a "
             "framediffuser.v1.RenderRequest; the session stays resumable"},
        Case{StreamController::Unreadable::kTooLarge, absl::StatusCode::kResourceExhausted,
             "request: 4321 bytes, more than --max_message_bytes"}}) {
    RecordingOutput output;
    auto controller = MakeController(&output);
    const v1::SessionOpened opened = Open(*controller, output);
    controller->OnUnreadableMessage(4321, c.why);
    const std::optional<absl::Status> finish = output.AwaitFinish();
    EXPECT_EQ(finish->code(), c.code) << *finish;
    EXPECT_THAT(std::string(finish->message()), HasSubstr(c.message));
    controller->Detach(/*call_cancelled=*/false);
    absl::StatusOr<std::shared_ptr<session::Session>> resumed =
        store_->Resume(opened.session_id(), opened.resume_token(), "alice");
    EXPECT_TRUE(resumed.ok()) << resumed.status();
  }
}

// A broken call (cancel) leaves the session resumable; a new stream
// resumes it: kResuming until released, then kOpen with the answer.
TEST_F(StreamControllerTest, CancelLeavesTheSessionResumable) {
  RecordingOutput first_output;
  auto first = MakeController(&first_output);
  const v1::SessionOpened opened = Open(*first, first_output);
  first->OnRead(MakeFrame(0));
  first_output.AwaitWrites(2);
  first->OnReadFailed(/*cancelled=*/true);
  first->OnCancel();
  EXPECT_EQ(first_output.AwaitFinish()->code(), absl::StatusCode::kCancelled);
  first->Detach(/*call_cancelled=*/true);

  RecordingOutput output;
  auto second = MakeController(&output);
  EXPECT_EQ(second->OnRead(MakeResume(opened.session_id(), opened.resume_token())),
            opened.session_id());
  EXPECT_EQ(second->phase(), StreamPhase::kResuming);
  second->OnSessionReleased();  // what the service's TakeOver does
  const std::vector<v1::RenderResponse> writes = output.AwaitWrites(1);
  ASSERT_TRUE(writes[0].has_opened());
  EXPECT_TRUE(writes[0].opened().resumed());
  EXPECT_EQ(writes[0].opened().last_frame_index(), 0u);
  EXPECT_EQ(second->phase(), StreamPhase::kOpen);
  second->Detach(/*call_cancelled=*/false);
}

// Drain: a DRAINING notice at once, frames already read are answered, then
// UNAVAILABLE; nothing more is read.
TEST_F(StreamControllerTest, DrainAnswersWhatWasReadThenEnds) {
  GateFirstSteps();
  RecordingOutput output;
  auto controller = MakeController(&output);
  Open(*controller, output);
  controller->OnRead(MakeFrame(0));
  stepping_->WaitForNotification();  // frame 0 is rendering
  const int reads = output.reads();
  controller->Drain();
  EXPECT_EQ(controller->phase(), StreamPhase::kDraining);
  EXPECT_TRUE(output.AwaitWrites(2)[1].has_notice());  // at once
  EXPECT_FALSE(output.finished());
  gate_->Open();
  const std::optional<absl::Status> finish = output.AwaitFinish();
  EXPECT_EQ(output.reads(), reads);
  EXPECT_EQ(finish->code(), absl::StatusCode::kUnavailable);
  const std::vector<v1::RenderResponse> writes = output.AwaitWrites(3);
  EXPECT_TRUE(writes[1].has_notice());
  EXPECT_EQ(writes[1].notice().reason(), v1::SessionNotice::REASON_DRAINING);
  EXPECT_TRUE(writes[2].has_frame());
  controller->Detach(/*call_cancelled=*/false);
}

// Taken over by another stream: ABORTED, and the frame it left rendering
// releases the session when it completes.
TEST_F(StreamControllerTest, LosingToATakeoverAbortsAndReleasesTheSession) {
  GateFirstSteps();
  RecordingOutput output;
  auto controller = MakeController(&output);
  const v1::SessionOpened opened = Open(*controller, output);
  controller->OnRead(MakeFrame(0));
  stepping_->WaitForNotification();  // frame 0 is rendering
  controller->LoseToTakeover();
  EXPECT_EQ(output.AwaitFinish()->code(), absl::StatusCode::kAborted);
  controller->Detach(/*call_cancelled=*/false);  // the RPC ends before the frame does
  gate_->Open();
  // The cancelled frame's callback (the controller outlived its reactor)
  // tells the service that the session is free.
  absl::MutexLock lock(&released_mu_);
  released_mu_.Await(absl::Condition(
      +[](std::vector<std::string>* released) { return !released->empty(); }, &released_));
  ASSERT_EQ(released_.size(), 1u);
  EXPECT_EQ(released_[0], opened.session_id());
}

TEST(StreamPhaseTest, NamesEveryPhase) {
  EXPECT_EQ(StreamPhaseName(StreamPhase::kOpening), "opening");
  EXPECT_EQ(StreamPhaseName(StreamPhase::kOpen), "open");
  EXPECT_EQ(StreamPhaseName(StreamPhase::kResuming), "resuming");
  EXPECT_EQ(StreamPhaseName(StreamPhase::kDraining), "draining");
  EXPECT_EQ(StreamPhaseName(StreamPhase::kClosed), "closed");
}

}  // namespace
}  // namespace fd::server

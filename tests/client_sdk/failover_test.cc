// SDK failover against the FakeRenderServer: streams broken at chosen
// points, a server restart mid-sequence, a draining server. In every case
// the caller gets every frame exactly once, in order, with the outputs an
// uninterrupted session would have produced.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <future>
#include <mutex>

#include "client_sdk/client.h"
#include "tests/client_sdk/sdk_fixture.h"

namespace fd::client {
namespace {

using testing::ExpectedSequence;
using ::testing::HasSubstr;
using testing::MakeFrames;
using testing::ResultLog;
using testing::SdkTest;
using testing::TestFrame;
using BreakPoint = fd::testing::FakeRenderServer::BreakPoint;

class FailoverTest : public SdkTest {
 protected:
  SessionOptions OptionsWithLog() {
    SessionOptions options = DefaultSessionOptions();
    options.on_failover = [this](const FailoverEvent& event) {
      std::lock_guard<std::mutex> lock(mu_);
      events_.push_back(event);
    };
    return options;
  }

  // Submits every frame asynchronously and waits for all answers.
  std::vector<absl::StatusOr<Frame>> RenderAll(Session* session,
                                               const std::vector<TestFrame>& frames,
                                               ResultLog* log) {
    for (const TestFrame& frame : frames) {
      absl::Status submitted = session->Submit(
          frame.request(),
          [log, index = frame.index](absl::StatusOr<Frame> r) { log->Add(std::move(r), index); });
      EXPECT_TRUE(submitted.ok()) << submitted;
    }
    EXPECT_TRUE(log->WaitFor(frames.size()));
    return log->results();
  }

  // Every index exactly once, in order, each equal to the uninterrupted run.
  void ExpectCompleteSequence(const std::vector<absl::StatusOr<Frame>>& results,
                              const std::vector<TestFrame>& frames) {
    const std::vector<Image8> expected = ExpectedSequence(frames);
    ASSERT_EQ(results.size(), frames.size());
    for (size_t i = 0; i < frames.size(); ++i) {
      ASSERT_TRUE(results[i].ok()) << "frame " << i << ": " << results[i].status();
      EXPECT_EQ(results[i]->frame_index, frames[i].index);
      EXPECT_EQ(results[i]->ToImage8(), expected[i]) << "frame " << i;
    }
  }

  std::vector<FailoverEvent> events() {
    std::lock_guard<std::mutex> lock(mu_);
    return events_;
  }

  std::mutex mu_;
  std::vector<FailoverEvent> events_;
};

TEST_F(FailoverTest, ResumesWhenTheServerStillHasTheSession) {
  const std::vector<TestFrame> frames = MakeFrames(12);
  std::unique_ptr<Session> session = Open(OptionsWithLog());
  ASSERT_NE(session, nullptr);
  const std::string id = session->session_id();
  server_->BreakOnFrame(5, BreakPoint::kBeforeRender);
  ResultLog log;
  ExpectCompleteSequence(RenderAll(session.get(), frames, &log), frames);
  EXPECT_EQ(session->failover_count(), 1);
  ASSERT_EQ(events().size(), 1u);
  EXPECT_TRUE(events()[0].resumed);
  EXPECT_EQ(events()[0].cause.code(), absl::StatusCode::kUnavailable);
  EXPECT_EQ(events()[0].old_session_id, id);
  EXPECT_EQ(events()[0].new_session_id, id);
  EXPECT_EQ(events()[0].last_frame_index, std::optional<uint64_t>(4));
  EXPECT_GE(events()[0].resent_frames, 1);
  EXPECT_EQ(server_->sessions_opened(), 1);
  EXPECT_EQ(server_->sessions_resumed(), 1);
  // The resume carried x-session-id for a sticky balancer.
  const std::vector<std::string> headers = server_->x_session_id_headers();
  ASSERT_EQ(headers.size(), 2u);
  EXPECT_EQ(headers[1], id);
  EXPECT_EQ(session->session_id(), id);
  EXPECT_TRUE(session->Close().ok());
}

TEST_F(FailoverTest, NewSessionWhenRenderedAnswersWereLost) {
  // The server renders frame 5 but its answer is lost: the resumable session
  // is one frame ahead of the client, so the SDK starts a new session from
  // frame 4's output and renders frame 5 again.
  const std::vector<TestFrame> frames = MakeFrames(10);
  std::unique_ptr<Session> session = Open(OptionsWithLog());
  ASSERT_NE(session, nullptr);
  const std::string first_id = session->session_id();
  server_->BreakOnFrame(5, BreakPoint::kAfterRender);
  ResultLog log;
  ExpectCompleteSequence(RenderAll(session.get(), frames, &log), frames);
  ASSERT_EQ(events().size(), 1u);
  EXPECT_FALSE(events()[0].resumed);
  EXPECT_NE(events()[0].new_session_id, first_id);
  EXPECT_EQ(session->session_id(), events()[0].new_session_id);
  EXPECT_EQ(server_->sessions_opened(), 2);
  EXPECT_TRUE(session->Close().ok());
}

TEST_F(FailoverTest, ServerRestartMidSequence) {
  const std::vector<TestFrame> frames = MakeFrames(20);
  std::unique_ptr<Session> session = Open(OptionsWithLog());
  ASSERT_NE(session, nullptr);
  const int port = server_->port();
  std::promise<void> reached;
  ResultLog log;
  for (const TestFrame& frame : frames) {
    ASSERT_TRUE(session
                    ->Submit(frame.request(),
                             [&, index = frame.index](absl::StatusOr<Frame> result) {
                               log.Add(std::move(result), index);
                               if (index == 7) reached.set_value();
                             })
                    .ok());
    if (frame.index == 9) {
      // Stop and restart the server (losing its sessions) while frames are
      // in flight, on the same port.
      reached.get_future().wait();
      server_->Stop();
      ASSERT_TRUE(server_->Start().ok());
      ASSERT_EQ(server_->port(), port);
    }
  }
  ASSERT_TRUE(log.WaitFor(frames.size()));
  ExpectCompleteSequence(log.results(), frames);
  EXPECT_GE(session->failover_count(), 1);
  ASSERT_FALSE(events().empty());
  EXPECT_FALSE(events().back().resumed);  // the restarted server had lost the session
  EXPECT_EQ(static_cast<int>(events().size()), session->failover_count());
  EXPECT_TRUE(session->Close().ok());
}

TEST_F(FailoverTest, DrainingServerIsNotResumed) {
  const std::vector<TestFrame> frames = MakeFrames(8);
  std::unique_ptr<Session> session = Open(OptionsWithLog());
  ASSERT_NE(session, nullptr);
  ResultLog log;
  for (const TestFrame& frame : frames) {
    ASSERT_TRUE(session
                    ->Submit(frame.request(),
                             [&, index = frame.index](absl::StatusOr<Frame> r) {
                               log.Add(std::move(r), index);
                             })
                    .ok());
    if (frame.index == 3) {
      ASSERT_TRUE(log.WaitFor(3));
      server_->Drain();
    }
  }
  ASSERT_TRUE(log.WaitFor(frames.size()));
  ExpectCompleteSequence(log.results(), frames);
  ASSERT_EQ(events().size(), 1u);
  EXPECT_FALSE(events()[0].resumed);
  EXPECT_EQ(server_->sessions_resumed(), 0);  // the notice said: do not resume
  EXPECT_EQ(server_->sessions_opened(), 2);
  EXPECT_TRUE(session->Close().ok());
}

TEST_F(FailoverTest, GivesUpAfterTheTimeout) {
  SessionOptions options = OptionsWithLog();
  options.failover_timeout = absl::Milliseconds(300);
  std::unique_ptr<Session> session = Open(options);
  ASSERT_NE(session, nullptr);
  ASSERT_TRUE(session->Render(TestFrame(0).request()).ok());
  server_->Stop();  // and never back
  absl::StatusOr<Frame> lost = session->Render(TestFrame(1).request());
  EXPECT_FALSE(lost.ok());
  EXPECT_THAT(lost.status().message(), HasSubstr("failover failed"));
  EXPECT_TRUE(events().empty());
  EXPECT_FALSE(session->Close().ok());
}

}  // namespace
}  // namespace fd::client

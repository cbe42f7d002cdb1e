// CompanionThread (model/runtime/companion_thread.h): work runs on another
// thread, at one intra-op thread, with the caller's inference mode; errors
// come back to the caller; an unjoined CompanionWork still waits.
#include "model/runtime/companion_thread.h"

#include <ATen/Parallel.h>
#include <gtest/gtest.h>
#include <torch/torch.h>

#include <atomic>
#include <stdexcept>
#include <string>
#include <thread>

namespace fd::model {
namespace {

TEST(CompanionThreadTest, RunsWorkOnItsOwnSingleThreadedThread) {
  at::set_num_threads(2);
  CompanionThread& companion = CompanionThread::ForCurrentThread();
  EXPECT_EQ(&companion, &CompanionThread::ForCurrentThread());
  std::thread::id work_thread;
  int work_intra_op_threads = 0;
  bool work_inference_mode = false;
  {
    torch::InferenceMode inference_mode;
    CompanionWork work(companion, [&] {
      work_thread = std::this_thread::get_id();
      work_intra_op_threads = at::get_num_threads();
      work_inference_mode = c10::InferenceMode::is_enabled();
    });
    work.Join();
  }
  EXPECT_NE(work_thread, std::this_thread::get_id());
  EXPECT_EQ(work_intra_op_threads, 1);
  EXPECT_TRUE(work_inference_mode);
  EXPECT_EQ(at::get_num_threads(), 2);  // the caller's own count is untouched

  // Outside inference mode, the work is too; the same thread serves again.
  std::thread::id again;
  CompanionWork work(companion, [&] {
    again = std::this_thread::get_id();
    work_inference_mode = c10::InferenceMode::is_enabled();
  });
  work.Join();
  EXPECT_EQ(again, work_thread);
  EXPECT_FALSE(work_inference_mode);
}

TEST(CompanionThreadTest, EachThreadHasItsOwnCompanion) {
  const CompanionThread* here = &CompanionThread::ForCurrentThread();
  const CompanionThread* there = nullptr;
  std::thread other([&] { there = &CompanionThread::ForCurrentThread(); });
  other.join();
  EXPECT_NE(here, there);
}

TEST(CompanionThreadTest, ErrorsReachTheCaller) {
  CompanionThread& companion = CompanionThread::ForCurrentThread();
  CompanionWork throws(companion, [] { throw std::runtime_error("from the companion"); });
  EXPECT_THROW(
      {
        try {
          throws.Join();
        } catch (const std::runtime_error& e) {
          EXPECT_STREQ(e.what(), "from the companion");
          throw;
        }
      },
      std::runtime_error);
  // A torch error too, and the companion serves on afterwards.
  CompanionWork torch_error(companion, [] { (void)torch::ones({2}).view({3}); });
  try {
    torch_error.Join();
    ADD_FAILURE() << "no error";
  } catch (const std::exception& e) {
    EXPECT_NE(std::string(e.what()).find("shape '[3]' is invalid"), std::string::npos) << e.what();
  }
  bool ran = false;
  CompanionWork fine(companion, [&] { ran = true; });
  fine.Join();
  EXPECT_TRUE(ran);
}

// The caller leaves early (as on an error of its own half): the destructor
// waits for the work, which still reads the caller's stack.
TEST(CompanionThreadTest, UnjoinedWorkIsWaitedFor) {
  std::atomic<int64_t> sum{0};
  {
    CompanionWork work(CompanionThread::ForCurrentThread(), [&] {
      int64_t local = 0;
      for (int64_t i = 0; i < 20'000'000; ++i) local += i % 7;
      sum = local;
    });
  }
  EXPECT_GT(sum.load(), 0);
  // Waiting swallowed nothing the next work would see.
  bool ran = false;
  CompanionWork next(CompanionThread::ForCurrentThread(), [&] { ran = true; });
  next.Join();
  EXPECT_TRUE(ran);
}

}  // namespace
}  // namespace fd::model

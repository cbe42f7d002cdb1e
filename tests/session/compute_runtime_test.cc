// What the server configures through session/ without LibTorch: load
// options from --device / --dtype, and the session <-> model enum mapping.
#include "session/compute_runtime.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <string>

#include "absl/strings/str_cat.h"
#include "session/model_enums.h"

namespace fd::session {
namespace {

using ::testing::HasSubstr;

TEST(ComputeRuntimeTest, ParsesDeviceAndDtype) {
  absl::StatusOr<EnvironmentLoadOptions> options = ParseLoadOptions("cpu", "float32");
  ASSERT_TRUE(options.ok()) << options.status();
  EXPECT_TRUE(IsCpuDevice(*options));
  EXPECT_EQ(DeviceName(*options), "cpu");
  EXPECT_EQ(options->dtype, torch::kFloat32);
  options = ParseLoadOptions("cuda:1", "bfloat16");
  ASSERT_TRUE(options.ok()) << options.status();
  EXPECT_FALSE(IsCpuDevice(*options));
  EXPECT_EQ(DeviceName(*options), "cuda:1");
  EXPECT_EQ(options->dtype, torch::kBFloat16);
  EXPECT_EQ(ParseLoadOptions("cpu", "float16")->dtype, torch::kFloat16);
}

TEST(ComputeRuntimeTest, BadFlagsAreNamed) {
  absl::StatusOr<EnvironmentLoadOptions> options = ParseLoadOptions("gpu0", "float32");
  EXPECT_EQ(options.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(options.status().message()),
              HasSubstr("--device: invalid device 'gpu0'"));
  options = ParseLoadOptions("cpu", "int8");
  EXPECT_EQ(options.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(options.status().message()),
              HasSubstr("--dtype: expected float32, float16 or bfloat16, got 'int8'"));
}

TEST(ComputeRuntimeTest, ReportsTheTorchVersion) { EXPECT_FALSE(TorchVersion().empty()); }

// (cores, cpu, max batch, --scheduler_workers, --threads) -> workers x threads.
struct ThreadsCase {
  WorkerThreadsRequest request;
  int workers;
  int threads;
  bool oversubscribed;
};

TEST(ResolveWorkerThreadsTest, FollowsTheThreadingPolicy) {
  const ThreadsCase cases[] = {
      // auto on a CPU: one single-threaded worker per core, capped by the batch.
      {{2, true, 4, 0, 0}, 2, 1, false},
      {{8, true, 4, 0, 0}, 4, 2, false},
      {{2, true, 1, 0, 0}, 1, 2, false},
      // --threads alone: the workers that leave every thread a core.
      {{2, true, 4, 0, 2}, 1, 2, false},
      {{8, true, 4, 0, 2}, 4, 2, false},
      {{2, true, 4, 0, 4}, 1, 4, true},
      // --scheduler_workers alone: the cores divided among them.
      {{2, true, 4, 1, 0}, 1, 2, false},
      {{2, true, 4, 4, 0}, 4, 1, true},
      // both: kept as given, oversubscription reported.
      {{2, true, 4, 2, 2}, 2, 2, true},
      {{4, true, 4, 2, 2}, 2, 2, false},
      // a GPU: one worker.
      {{16, false, 8, 0, 0}, 1, 16, false},
      {{16, false, 8, 0, 2}, 1, 2, false},
  };
  for (const ThreadsCase& c : cases) {
    const WorkerThreads got = ResolveWorkerThreads(c.request);
    const std::string label = absl::StrCat("cores ", c.request.cores, " cpu ", c.request.cpu,
                                           " batch ", c.request.max_batch_size, " workers ",
                                           c.request.workers, " threads ", c.request.threads);
    EXPECT_EQ(got.workers, c.workers) << label;
    EXPECT_EQ(got.threads_per_worker, c.threads) << label;
    EXPECT_EQ(got.oversubscribed, c.oversubscribed) << label;
  }
}

TEST(ModelEnumsTest, EverySessionValueMapsToTheModelAndBack) {
  for (SchedulerKind kind : {SchedulerKind::kUniPC, SchedulerKind::kDpmSolverPP2M,
                             SchedulerKind::kDDIM, SchedulerKind::kEulerDiscrete}) {
    EXPECT_EQ(FromModelScheduler(ToModelScheduler(kind)), kind);
  }
  for (SkyMode mode : {SkyMode::kClientImage, SkyMode::kPreviousOutput, SkyMode::kOff}) {
    EXPECT_EQ(FromModelSkyMode(ToModelSkyMode(mode)), mode);
  }
  EXPECT_EQ(ToModelScheduler(SchedulerKind::kDpmSolverPP2M),
            model::SchedulerType::kDPMSolverMultistep);
  EXPECT_EQ(ToModelSkyMode(SkyMode::kClientImage), model::SkyFillMode::kSkyImage);
}

}  // namespace
}  // namespace fd::session

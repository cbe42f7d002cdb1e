// What the server configures through session/ without LibTorch: load
// options from --device / --dtype, and the session <-> model enum mapping.
#include "session/compute_runtime.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <string>

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

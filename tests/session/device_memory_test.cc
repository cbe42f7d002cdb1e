// Memory in use on a device, named as on the server's command line (moved
// here from tests/server with session/device_memory.h).
#include "session/device_memory.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <string>

namespace fd::session {
namespace {

using ::testing::HasSubstr;

TEST(DeviceMemoryTest, CpuIsTheResidentSetSize) {
  const absl::StatusOr<int64_t> bytes = DeviceMemoryInUseBytes("cpu");
  ASSERT_TRUE(bytes.ok()) << bytes.status();
  // A process with LibTorch loaded is resident in more than a megabyte.
  EXPECT_GT(*bytes, 1 << 20);
}

#ifndef FD_WITH_CUDA
TEST(DeviceMemoryTest, CudaIsUnimplementedInACpuBuildAndNamesTheDevice) {
  const absl::StatusOr<int64_t> bytes = DeviceMemoryInUseBytes("cuda:0");
  EXPECT_EQ(bytes.status().code(), absl::StatusCode::kUnimplemented);
  EXPECT_THAT(std::string(bytes.status().message()), HasSubstr("cuda:0"));
}
#endif

TEST(DeviceMemoryTest, AnUnparsableDeviceNameIsInvalidArgument) {
  const absl::StatusOr<int64_t> bytes = DeviceMemoryInUseBytes("toaster:9");
  EXPECT_EQ(bytes.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(bytes.status().message()), HasSubstr("toaster:9"));
}

}  // namespace
}  // namespace fd::session

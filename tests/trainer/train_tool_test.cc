// framediffuser-train as a user runs it: --help, a bad flag, and SIGINT
// writing a checkpoint that --resume continues.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <string>
#include <vector>

#include "absl/strings/match.h"
#include "tests/testing/run_tool.h"
#include "tests/trainer/trainer_test_util.h"

namespace fd::trainer {
namespace {

namespace fs = std::filesystem;

using fd::testing::ToolResult;

ToolResult RunTool(const std::string& args) { return fd::testing::RunTool(FD_TRAIN_TOOL, args); }

TEST(TrainToolTest, HelpAndBadFlags) {
  ToolResult help = RunTool("--help");
  EXPECT_EQ(help.exit_code, 0);
  EXPECT_TRUE(absl::StrContains(help.output, "usage: framediffuser-train")) << help.output;
  ToolResult bad = RunTool("all --data /d --out /o --batch_size x");
  EXPECT_EQ(bad.exit_code, 2);
  EXPECT_TRUE(absl::StrContains(bad.output, "--batch_size: expected an integer")) << bad.output;
  ToolResult missing = RunTool("all --data /nonexistent --out /tmp/fd_never_written");
  EXPECT_EQ(missing.exit_code, 1);
  EXPECT_TRUE(absl::StrContains(missing.output, "/nonexistent")) << missing.output;
}

TEST(TrainToolTest, SigintWritesACheckpointThatResumeContinues) {
  const std::string dir = testing::MakeTempDir("tool");
  testing::WriteSequence(dir + "/data", {5, 32, 32, 4, true, true});
  const std::string out = dir + "/out";
  const std::vector<std::string> args = {FD_TRAIN_TOOL,   "stage0",       "--data",
                                         dir + "/data",   "--out",        out,
                                         "--resolution",  "32x32",        "--vae_steps",
                                         "1000000",       "--log_every",  "1",
                                         "--no-progress", "--batch_size", "1"};
  int pipe_fds[2];
  ASSERT_EQ(pipe(pipe_fds), 0);
  const pid_t pid = fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {
    dup2(pipe_fds[1], STDERR_FILENO);
    close(pipe_fds[0]);
    std::vector<char*> argv;
    for (const std::string& a : args) argv.push_back(const_cast<char*>(a.c_str()));
    argv.push_back(nullptr);
    execv(argv[0], argv.data());
    _exit(127);
  }
  close(pipe_fds[1]);
  // Wait (by reading its output, no sleeps) until training has started.
  std::string output;
  char buffer[1024];
  while (!absl::StrContains(output, "[stage0-vae] step 2/")) {
    const ssize_t n = read(pipe_fds[0], buffer, sizeof(buffer));
    if (n <= 0) break;
    output.append(buffer, static_cast<size_t>(n));
  }
  ASSERT_TRUE(absl::StrContains(output, "[stage0-vae] step 2/")) << output;
  kill(pid, SIGINT);
  for (ssize_t n; (n = read(pipe_fds[0], buffer, sizeof(buffer))) > 0;) {
    output.append(buffer, static_cast<size_t>(n));
  }
  close(pipe_fds[0]);
  int status = 0;
  ASSERT_EQ(waitpid(pid, &status, 0), pid);
  ASSERT_TRUE(WIFEXITED(status)) << output;
  EXPECT_EQ(WEXITSTATUS(status), 130) << output;
  EXPECT_TRUE(absl::StrContains(output, "--resume")) << output;
  ASSERT_TRUE(fs::exists(out + "/checkpoints/LATEST"));

  ToolResult refused = RunTool("stage0 --data " + dir + "/data --out " + out +
                               " --resolution 32x32 --no-progress --batch_size 1");
  EXPECT_EQ(refused.exit_code, 1);
  EXPECT_TRUE(absl::StrContains(refused.output, "pass --resume")) << refused.output;
  ToolResult resumed = RunTool("stage0 --data " + dir + "/data --out " + out +
                               " --resolution 32x32 --no-progress --batch_size 1 --resume"
                               " --vae_steps 3 --base_steps 2");
  EXPECT_EQ(resumed.exit_code, 0) << resumed.output;
  EXPECT_TRUE(absl::StrContains(resumed.output, "resumed")) << resumed.output;
  EXPECT_TRUE(fs::exists(out + "/unet/diffusion_pytorch_model.safetensors"));
  fs::remove_all(dir);
}

}  // namespace
}  // namespace fd::trainer

#include "tools/scenegen/cli.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <sys/wait.h>

#include <cstdio>
#include <filesystem>

#include "tests/scenegen/scenegen_test_util.h"
#include "tests/testing/run_tool.h"

namespace fd::scenegen {
namespace {

using ::testing::HasSubstr;

absl::StatusOr<CliCommand> Parse(std::vector<std::string> args) { return ParseCommandLine(args); }

TEST(CliTest, ParsesEveryFlagInBothForms) {
  absl::StatusOr<CliCommand> c =
      Parse({"--scene", "room", "--frames=7", "--start", "3", "--size", "96x48", "--seed=42",
             "--out", "/tmp/x", "--format", "both", "--threads=3"});
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_EQ(c->action, CliCommand::Action::kGenerate);
  EXPECT_EQ(c->options.scene, "room");
  EXPECT_EQ(c->options.frames, 7);
  EXPECT_EQ(c->options.start_frame, 3);
  EXPECT_EQ(c->options.width, 96);
  EXPECT_EQ(c->options.height, 48);
  EXPECT_EQ(c->options.seed, 42u);
  EXPECT_EQ(c->options.out_dir, "/tmp/x");
  EXPECT_EQ(c->options.format, OutputFormat::kBoth);
  EXPECT_EQ(c->options.threads, 3);
}

TEST(CliTest, DefaultsNeedOnlyOut) {
  absl::StatusOr<CliCommand> c = Parse({"--out", "d"});
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_EQ(c->options.scene, "street");
  EXPECT_EQ(c->options.format, OutputFormat::kPng);
  EXPECT_EQ(c->options.threads, 0);  // all cores
}

TEST(CliTest, HelpAndListScenesNeedNoOut) {
  EXPECT_EQ(Parse({"--help"})->action, CliCommand::Action::kHelp);
  EXPECT_EQ(Parse({"-h"})->action, CliCommand::Action::kHelp);
  EXPECT_EQ(Parse({"--list-scenes"})->action, CliCommand::Action::kListScenes);
  EXPECT_THAT(SceneListText(), HasSubstr("street"));
  EXPECT_THAT(SceneListText(), HasSubstr("room"));
  // The help documents the depth encoding and the layout.
  EXPECT_THAT(UsageText(), HasSubstr("near / d"));
  EXPECT_THAT(UsageText(), HasSubstr("FinalImage/FinalImage_0000.png"));
}

// Every error is INVALID_ARGUMENT and names the offending flag.
TEST(CliTest, BadFlagsNameTheFlag) {
  const struct {
    std::vector<std::string> args;
    std::string expected;
  } kCases[] = {
      {{"--out", "d", "--bogus", "1"}, "--bogus"},
      {{"--out", "d", "--frames", "abc"}, "--frames"},
      {{"--out", "d", "--frames", "0"}, "--frames"},
      {{"--out", "d", "--frames"}, "--frames: missing value"},
      {{"--out", "d", "--size", "64"}, "--size"},
      {{"--out", "d", "--size", "0x64"}, "--size"},
      {{"--out", "d", "--size", "64x64x3"}, "--size"},
      {{"--out", "d", "--seed", "-1"}, "--seed"},
      {{"--out", "d", "--format", "jpg"}, "--format"},
      {{"--out", "d", "--threads", "0"}, "--threads"},
      {{"--out", "d", "--start", "-2"}, "--start"},
      {{"--out", "d", "--scene", "moon"}, "--scene: unknown scene 'moon' (known: street, room)"},
      {{"--frames", "3"}, "--out"},
      {{"--out", "d", "stray"}, "stray"},
  };
  for (const auto& c : kCases) {
    absl::StatusOr<CliCommand> parsed = ParseCommandLine(c.args);
    ASSERT_FALSE(parsed.ok()) << c.expected;
    EXPECT_EQ(parsed.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(std::string(parsed.status().message()), HasSubstr(c.expected));
  }
}

using fd::testing::ToolResult;

ToolResult RunTool(const std::string& args) { return fd::testing::RunTool(FD_SCENEGEN_TOOL, args); }

TEST(CliToolTest, BadFlagsExitWithStatusTwoAndNameTheFlag) {
  ToolResult r = RunTool("--out /tmp/never --frames nope");
  EXPECT_EQ(r.exit_code, kExitUsage);
  EXPECT_THAT(r.output, HasSubstr("--frames"));
  r = RunTool("--out /tmp/never --no-such-flag");
  EXPECT_EQ(r.exit_code, kExitUsage);
  EXPECT_THAT(r.output, HasSubstr("--no-such-flag"));
  r = RunTool("--scene street");
  EXPECT_EQ(r.exit_code, kExitUsage);
  EXPECT_THAT(r.output, HasSubstr("--out"));
}

TEST(CliToolTest, HelpListAndGenerate) {
  ToolResult r = RunTool("--help");
  EXPECT_EQ(r.exit_code, kExitOk);
  EXPECT_THAT(r.output, HasSubstr("Depth encoding"));
  r = RunTool("--list-scenes");
  EXPECT_EQ(r.exit_code, kExitOk);
  EXPECT_THAT(r.output, HasSubstr("room"));

  const std::string dir = testing::FreshDir("cli_generate");
  r = RunTool("--scene room --frames 2 --size 24x16 --seed 5 --threads 2 --out " + dir);
  EXPECT_EQ(r.exit_code, kExitOk) << r.output;
  EXPECT_TRUE(std::filesystem::exists(dir + "/Metallic/Metallic_0001.png"));
  EXPECT_TRUE(std::filesystem::exists(dir + "/scene.json"));
  const Image8 depth = testing::ReadPngOrDie(dir + "/Depth/Depth_0001.png");
  EXPECT_EQ(depth.width, 24);
  EXPECT_EQ(depth.height, 16);
}

TEST(CliToolTest, UnwritableOutputExitsWithStatusOne) {
  const std::string dir = testing::FreshDir("cli_unwritable");
  std::ofstream(dir + "/file") << "x";  // a file where a folder must go
  const ToolResult r = RunTool("--frames 1 --size 8x8 --out " + dir + "/file");
  EXPECT_EQ(r.exit_code, kExitFailure);
  EXPECT_THAT(r.output, HasSubstr("error"));
}

}  // namespace
}  // namespace fd::scenegen

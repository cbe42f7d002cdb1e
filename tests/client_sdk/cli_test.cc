// framediffuser-client: argument parsing, progress formatting, and the
// commands run in-process (render against the FakeRenderServer, eval on
// files written here).
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "absl/strings/str_format.h"
#include "client_sdk/cli/args.h"
#include "client_sdk/cli/commands.h"
#include "client_sdk/cli/progress.h"
#include "client_sdk/cli/video.h"
#include "client_sdk/image_io.h"
#include "tests/client_sdk/sdk_fixture.h"

namespace fd::client::cli {
namespace {

using ::testing::HasSubstr;
using testing::Pattern8;
using testing::ScratchDir;
namespace fs = std::filesystem;

// Captures what a command writes to a FILE*.
class Capture {
 public:
  Capture() : file_(std::tmpfile()) {}
  ~Capture() { std::fclose(file_); }
  std::FILE* get() { return file_; }
  std::string str() {
    std::fflush(file_);
    std::rewind(file_);
    std::string text;
    char buffer[4096];
    size_t n;
    while ((n = std::fread(buffer, 1, sizeof(buffer), file_)) > 0) text.append(buffer, n);
    return text;
  }

 private:
  std::FILE* file_;
};

absl::StatusOr<Command> Parse(std::vector<std::string> args) { return ParseCommandLine(args); }

TEST(CliArgsTest, ParsesRender) {
  absl::StatusOr<Command> command = Parse({"--server",
                                           "host:1234",
                                           "render",
                                           "--env=tiny",
                                           "--input",
                                           "in",
                                           "--output",
                                           "out",
                                           "--frames",
                                           "3:9",
                                           "--steps",
                                           "4",
                                           "--seed",
                                           "11",
                                           "--format",
                                           "exr",
                                           "--keyframe-from-input",
                                           "--video",
                                           "v.mp4",
                                           "--side-by-side",
                                           "--no-failover"});
  ASSERT_TRUE(command.ok()) << command.status();
  EXPECT_EQ(command->kind, Command::Kind::kRender);
  EXPECT_EQ(command->connection.server, "host:1234");
  EXPECT_FALSE(command->connection.failover);
  const RenderArgs& r = command->render;
  EXPECT_EQ(r.environment, "tiny");
  EXPECT_EQ(r.input, "in");
  EXPECT_EQ(r.frames.first, std::optional<int64_t>(3));
  EXPECT_EQ(r.frames.end, std::optional<int64_t>(9));
  EXPECT_EQ(r.steps, 4u);
  EXPECT_EQ(r.seed, 11u);
  EXPECT_EQ(r.format, "exr");
  EXPECT_TRUE(r.keyframe_from_input);
  EXPECT_TRUE(r.side_by_side);
  EXPECT_EQ(r.video, "v.mp4");
}

TEST(CliArgsTest, ErrorsNameTheFlag) {
  struct Case {
    std::vector<std::string> args;
    std::string message;
  } cases[] = {
      {{"render", "--input", "a", "--output", "b"}, "--env: required"},
      {{"render", "--env", "e", "--input", "a", "--output", "b", "--steps", "x"}, "--steps"},
      {{"render", "--env", "e", "--input", "a", "--output", "b", "--format", "gif"},
       "--format: unknown value 'gif'"},
      {{"render", "--env", "e", "--input", "a", "--output", "b", "--frames", "9:3"},
       "--frames: empty range"},
      {{"render", "--env", "e", "--input", "a", "--output", "b", "--keyframe", "k.png",
        "--keyframe-from-input"},
       "choose one keyframe source"},
      {{"render", "--env", "e", "--input", "a", "--output", "b", "--side-by-side"},
       "--side-by-side: needs --video"},
      {{"eval", "--gt", "g"}, "--pred: required"},
      {{"eval", "--pred", "p", "--gt", "g", "--env", "x"}, "--env: not a flag of 'eval'"},
      {{"frobnicate"}, "unknown command 'frobnicate'"},
      {{"envs", "--bogus"}, "unknown flag '--bogus'"},
      {{"envs", "--server"}, "--server: missing value"},
  };
  for (const Case& c : cases) {
    absl::StatusOr<Command> command = Parse(c.args);
    EXPECT_EQ(command.status().code(), absl::StatusCode::kInvalidArgument) << c.message;
    EXPECT_THAT(command.status().message(), HasSubstr(c.message));
  }
  absl::StatusOr<Command> help = Parse({});
  ASSERT_TRUE(help.ok());
  EXPECT_EQ(help->kind, Command::Kind::kHelp);
}

TEST(CliArgsTest, TokenFromEnvironmentAndFrameRanges) {
  absl::StatusOr<Command> command = ParseCommandLine({"envs"}, "from-env");
  ASSERT_TRUE(command.ok());
  EXPECT_EQ(command->connection.token, "from-env");
  command = ParseCommandLine({"envs", "--token", "flag"}, "from-env");
  EXPECT_EQ(command->connection.token, "flag");

  absl::StatusOr<FrameRange> open_end = ParseFrameRange("5:");
  ASSERT_TRUE(open_end.ok());
  EXPECT_TRUE(open_end->Contains(5));
  EXPECT_TRUE(open_end->Contains(1000));
  EXPECT_FALSE(open_end->Contains(4));
  absl::StatusOr<FrameRange> single = ParseFrameRange("7");
  ASSERT_TRUE(single.ok());
  EXPECT_TRUE(single->Contains(7));
  EXPECT_FALSE(single->Contains(8));
  EXPECT_FALSE(ParseFrameRange("a:b").ok());
  EXPECT_FALSE(ParseFrameRange("-1:3").ok());
}

TEST(CliProgressTest, Formats) {
  EXPECT_EQ(FormatDuration(27.4), "0:27");
  EXPECT_EQ(FormatDuration(3725), "1:02:05");
  EXPECT_EQ(FormatDuration(-1), "--:--");
  EXPECT_EQ(FormatProgressBar(5, 10, 4, 2.5, 2.0, 10),
            "[====>     ] 5/10  frame 4  2.50 fps  ETA 0:02");
  EXPECT_EQ(FormatProgressBar(10, 10, 9, 2.5, 0.0, 10),
            "[==========] 10/10  frame 9  2.50 fps  ETA 0:00");

  Capture plain;
  ProgressReporter reporter(plain.get(), 3, /*tty=*/false);
  reporter.FrameDone(0);
  reporter.Message("hello");
  reporter.FrameDone(1);
  reporter.FrameDone(2);
  reporter.Finish();
  const std::string text = plain.str();
  EXPECT_THAT(text, HasSubstr("progress: 1/3 frames (frame 0)"));
  EXPECT_THAT(text, HasSubstr("hello\n"));
  EXPECT_THAT(text, HasSubstr("progress: 3/3 frames (frame 2)"));
  EXPECT_EQ(text.find('\r'), std::string::npos);  // no bar redraws in logs

  Capture live;
  ProgressReporter bar(live.get(), 2, /*tty=*/true);
  bar.FrameDone(0);
  bar.Finish();
  EXPECT_THAT(live.str(), HasSubstr("\r[==============> "));
}

TEST(CliVideoTest, SideBySidePanels) {
  const Image8 a = Pattern8(8, 4, 3, 1);
  const Image8 gray = Pattern8(8, 4, 1, 2);
  const Image8 wrong = Pattern8(5, 5, 3, 3);
  const Image8 out = SideBySide({&a, &gray, &wrong}, {}, 8, 4);
  ASSERT_EQ(out.width, 24);
  EXPECT_EQ(out.at(3, 2, 1), a.at(3, 2, 1));
  EXPECT_EQ(out.at(8 + 3, 2, 0), gray.at(3, 2, 0));
  EXPECT_EQ(out.at(8 + 3, 2, 2), gray.at(3, 2, 0));
  EXPECT_EQ(out.at(16 + 3, 2, 0), 0);  // wrong size -> black
}

// Writes a dataset whose frames are the SDK fixture's TestFrames, plus a
// FinalImage ground truth per frame.
void WriteTestDataset(const fs::path& dir, int count) {
  for (const char* b : {"FinalImage", "BaseColor", "Normals", "Depth", "Roughness"}) {
    fs::create_directories(dir / b);
  }
  for (int i = 0; i < count; ++i) {
    const testing::TestFrame frame(i);
    auto path = [&](const char* buffer) {
      return (dir / buffer / absl::StrFormat("%s_%04d.png", buffer, i)).string();
    };
    ASSERT_TRUE(WritePng(path("BaseColor"), frame.basecolor).ok());
    ASSERT_TRUE(WritePng(path("Normals"), frame.normals).ok());
    ASSERT_TRUE(WritePng(path("Depth"), frame.depth).ok());
    ASSERT_TRUE(WritePng(path("Roughness"), frame.roughness).ok());
    ASSERT_TRUE(
        WritePng(path("FinalImage"), Pattern8(testing::kSize, testing::kSize, 3, 500 + i)).ok());
  }
}

class CliRenderTest : public testing::SdkTest {
 protected:
  Command RenderCommand(const std::string& input, const std::string& output) {
    Command command;
    command.kind = Command::Kind::kRender;
    command.connection.server = server_->address();
    command.render.environment = "tiny";
    command.render.input = input;
    command.render.output = output;
    return command;
  }
};

TEST_F(CliRenderTest, RendersADatasetWithVideoAndEvaluatesIt) {
  ScratchDir dir;
  WriteTestDataset(dir.path() / "in", 6);
  Command command = RenderCommand(dir / "in", dir / "out");
  command.render.keyframe_from_input = true;
  command.render.frames = *ParseFrameRange("0:5");
  command.render.video = dir / "video.mp4";
  command.render.side_by_side = true;
  Capture out, err;
  ASSERT_EQ(RunRender(command, out.get(), err.get(), /*tty=*/false), kExitOk) << err.str();
  EXPECT_THAT(out.str(), HasSubstr("done: 5/5 frames"));
  EXPECT_THAT(err.str(), HasSubstr("progress: 5/5 frames"));

  // Frame 0 has no predecessor: the keyframe is its own ground truth.
  const Image8 keyframe = Pattern8(testing::kSize, testing::kSize, 3, 500);
  const std::vector<Image8> expected = testing::ExpectedSequence(testing::MakeFrames(5), keyframe);
  for (int i = 0; i < 5; ++i) {
    absl::StatusOr<Image8> written =
        ReadPng(dir / absl::StrFormat("out/FinalImage/FinalImage_%04d.png", i));
    ASSERT_TRUE(written.ok()) << written.status();
    EXPECT_EQ(*written, expected[i]) << "frame " << i;
  }
  EXPECT_FALSE(fs::exists(dir / "out/FinalImage/FinalImage_0005.png"));
  ASSERT_TRUE(fs::exists(dir / "video.mp4"));
  EXPECT_GT(fs::file_size(dir / "video.mp4"), 1000u);

  // eval: the rendered frames against the input's ground truth.
  Command eval;
  eval.kind = Command::Kind::kEval;
  eval.eval.pred = dir / "out";
  eval.eval.gt = dir / "in";
  eval.eval.csv = dir / "metrics.csv";
  eval.eval.plot = dir / "metrics.png";
  Capture eval_out, eval_err;
  ASSERT_EQ(RunEval(eval, eval_out.get(), eval_err.get()), kExitOk) << eval_err.str();
  EXPECT_THAT(eval_out.str(), HasSubstr("mean over 5 frames"));
  std::ifstream csv(dir / "metrics.csv");
  std::stringstream text;
  text << csv.rdbuf();
  EXPECT_THAT(text.str(), ::testing::StartsWith("frame,psnr_db,ssim\n0,"));
  EXPECT_THAT(text.str(), HasSubstr("\nmean,"));
  absl::StatusOr<Image8> plot = ReadPng(dir / "metrics.png");
  ASSERT_TRUE(plot.ok()) << plot.status();
  EXPECT_EQ(plot->width, 960);
}

TEST_F(CliRenderTest, ExrOutputAndPlainFolderEval) {
  ScratchDir dir;
  WriteTestDataset(dir.path() / "in", 2);
  Command command = RenderCommand(dir / "in", dir / "out");
  command.render.format = "exr";
  Capture out, err;
  ASSERT_EQ(RunRender(command, out.get(), err.get(), false), kExitOk) << err.str();
  absl::StatusOr<ImageF> frame = ReadExr(dir / "out/FinalImage/FinalImage_0001.exr");
  ASSERT_TRUE(frame.ok()) << frame.status();
  EXPECT_EQ(frame->channels, 3);
}

TEST_F(CliRenderTest, ClearErrors) {
  ScratchDir dir;
  WriteTestDataset(dir.path() / "in", 2);
  {
    Command command = RenderCommand(dir / "in", dir / "out");
    command.render.environment = "nope";
    Capture out, err;
    EXPECT_EQ(RunRender(command, out.get(), err.get(), false), kExitFailure);
    EXPECT_THAT(err.str(), HasSubstr("has no environment 'nope' (available: tiny)"));
  }
  {
    Command command = RenderCommand(dir / "in", dir / "out");
    command.render.frames = *ParseFrameRange("0:1");
    server_->Stop();
    Capture out, err;
    EXPECT_EQ(RunRender(command, out.get(), err.get(), false), kExitFailure);
    EXPECT_THAT(err.str(), HasSubstr("cannot reach the FrameDiffuser server at"));
  }
  {
    fs::remove(dir.path() / "in/Depth/Depth_0001.png");
    Command command = RenderCommand(dir / "in", dir / "out");
    Capture out, err;
    EXPECT_EQ(RunRender(command, out.get(), err.get(), false), kExitFailure);
    EXPECT_THAT(err.str(), HasSubstr("missing Depth buffer for frame 1"));
  }
}

TEST_F(CliRenderTest, EnvsAndHealth) {
  Command command;
  command.kind = Command::Kind::kEnvs;
  command.connection.server = server_->address();
  Capture out, err;
  ASSERT_EQ(RunEnvs(command, out.get(), err.get()), kExitOk) << err.str();
  EXPECT_THAT(out.str(), HasSubstr("tiny"));
  EXPECT_THAT(out.str(), HasSubstr("ready"));
  command.kind = Command::Kind::kHealth;
  Capture health_out, health_err;
  ASSERT_EQ(RunHealth(command, health_out.get(), health_err.get()), kExitOk);
  EXPECT_THAT(health_out.str(), HasSubstr("serving"));
}

TEST(CliEvalTest, KnownNoiseAndMismatches) {
  ScratchDir dir;
  fs::create_directories(dir.path() / "gt");
  fs::create_directories(dir.path() / "pred");
  for (int i = 0; i < 3; ++i) {
    Image8 gt(16, 16, 3);
    for (size_t k = 0; k < gt.pixels.size(); ++k) gt.pixels[k] = static_cast<uint8_t>(20 + k % 200);
    Image8 pred = gt;
    if (i > 0) {
      for (size_t k = 0; k < pred.pixels.size(); ++k) pred.pixels[k] += (k % 2 == 0) ? 5 : -5;
    }
    ASSERT_TRUE(WritePng(dir / absl::StrFormat("gt/frame_%04d.png", i), gt).ok());
    ASSERT_TRUE(WritePng(dir / absl::StrFormat("pred/shot_%04d.png", i), pred).ok());
  }
  Command command;
  command.kind = Command::Kind::kEval;
  command.eval.pred = dir / "pred";
  command.eval.gt = dir / "gt";
  command.eval.csv = dir / "m.csv";
  Capture out, err;
  ASSERT_EQ(RunEval(command, out.get(), err.get()), kExitOk) << err.str();
  // Frame 0 is identical (infinite PSNR, left out of the mean); frames 1, 2
  // have PSNR 20 log10(51).
  EXPECT_THAT(out.str(), HasSubstr(absl::StrFormat("mean over 3 frames: PSNR %.3f dB",
                                                   20 * std::log10(51.0))));
  EXPECT_THAT(out.str(), HasSubstr("1 identical frame(s)"));
  std::ifstream csv(dir / "m.csv");
  std::string header, first;
  std::getline(csv, header);
  std::getline(csv, first);
  EXPECT_EQ(first, "0,inf,1.000000");

  // A prediction without ground truth.
  ASSERT_TRUE(WritePng(dir / "pred/shot_0009.png", Image8(16, 16, 3)).ok());
  Capture out2, err2;
  EXPECT_EQ(RunEval(command, out2.get(), err2.get()), kExitFailure);
  EXPECT_THAT(err2.str(), HasSubstr("mismatched frame numbers"));
  EXPECT_THAT(err2.str(), HasSubstr("shot_0009.png has no ground truth frame 9"));
  fs::remove(dir.path() / "pred/shot_0009.png");

  // Different sizes.
  ASSERT_TRUE(WritePng(dir / "pred/shot_0002.png", Image8(8, 8, 3)).ok());
  Capture out3, err3;
  EXPECT_EQ(RunEval(command, out3.get(), err3.get()), kExitFailure);
  EXPECT_THAT(err3.str(), HasSubstr("size mismatch"));
  EXPECT_THAT(err3.str(), HasSubstr("shot_0002.png is 8x8"));
}

}  // namespace
}  // namespace fd::client::cli

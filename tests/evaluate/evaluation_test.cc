// tools/evaluate (framediffuser-evaluate's library) on four held-out-style
// street frames from the real scene generator and a random tiny environment.
#include "tools/evaluate/evaluation.h"

#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <string>

#include "absl/strings/match.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_split.h"
#include "client_sdk/image.h"
#include "client_sdk/image_io.h"
#include "client_sdk/metrics.h"
#include "model/presets/presets.h"
#include "nlohmann/json.hpp"
#include "tests/testing/run_tool.h"
#include "tools/evaluate/denoising.h"

namespace fd::evaluate {
namespace {

namespace fs = std::filesystem;
using fd::client::Image8;

constexpr int kFrames = 4;
constexpr int kSize = 64;

class EvaluationTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    root_ = new std::string(
        (fs::temp_directory_path() / absl::StrFormat("fd-evaluate-test-%d", ::getpid())).string());
    fs::remove_all(*root_);
    const fd::testing::ToolResult made = fd::testing::RunTool(
        FD_SCENEGEN_TOOL, absl::StrFormat("--scene street --seed 1 --start 0 --frames %d "
                                          "--size %dx%d --threads 1 --out %s/seq",
                                          kFrames, kSize, kSize, *root_));
    ASSERT_EQ(made.exit_code, 0) << made.output;
    fd::model::MakeCheckpointOptions checkpoint;
    checkpoint.preset = "tiny";
    checkpoint.out_dir = *root_ + "/env";
    checkpoint.seed = 7;
    absl::Status written = fd::model::MakeCheckpoint(checkpoint);
    ASSERT_TRUE(written.ok()) << written;
    std::ofstream(*root_ + "/env/environment.json")
        << absl::StrFormat(R"({"width": %d, "height": %d, "steps": 2})", kSize, kSize);
  }
  static void TearDownTestSuite() {
    fs::remove_all(*root_);
    delete root_;
    root_ = nullptr;
  }

  static std::string Seq() { return *root_ + "/seq"; }
  static std::string Env() { return *root_ + "/env"; }
  static std::string Path(const std::string& name) { return *root_ + "/" + name; }

  static Image8 Read(const std::string& path) {
    absl::StatusOr<fd::client::AnyImage> image = fd::client::ReadImage(path);
    EXPECT_TRUE(image.ok()) << image.status();
    return image.ok() ? fd::client::ToUint8(*image) : Image8();
  }
  static fd::client::ImageF Unit(const Image8& image) {
    fd::client::ImageF out(image.width, image.height, image.channels);
    for (size_t i = 0; i < image.pixels.size(); ++i) out.pixels[i] = image.pixels[i] / 255.0f;
    return out;
  }
  static std::string GroundTruth(int frame) {
    return absl::StrFormat("%s/FinalImage/FinalImage_%04d.png", Seq(), frame);
  }

  static std::string* root_;
};

std::string* EvaluationTest::root_ = nullptr;

TEST_F(EvaluationTest, RoundTripWritesOneDecodedFramePerGroundTruthFrame) {
  absl::StatusOr<int64_t> frames = WriteRoundTrip(Env(), Seq(), Path("rt"), 1);
  ASSERT_TRUE(frames.ok()) << frames.status();
  EXPECT_EQ(*frames, kFrames);
  for (int f = 0; f < kFrames; ++f) {
    const Image8 image = Read(absl::StrFormat("%s/RoundTrip_%04d.png", Path("rt"), f));
    EXPECT_EQ(image.width, kSize);
    EXPECT_EQ(image.height, kSize);
    EXPECT_EQ(image.channels, 3);
  }
  EXPECT_EQ(WriteRoundTrip(Env(), Path("missing"), Path("rt2"), 1).status().code(),
            absl::StatusCode::kNotFound);
}

TEST_F(EvaluationTest, ReportsThePsnrOfEachVariantAndWritesItsFiles) {
  // Variant "gray": every frame mid-gray, whose PSNR the test computes itself.
  fs::create_directories(Path("gray/FinalImage"));
  double expected_psnr = 0;
  for (int f = 0; f < kFrames; ++f) {
    Image8 gray(kSize, kSize, 3);
    std::fill(gray.pixels.begin(), gray.pixels.end(), 128);
    ASSERT_TRUE(fd::client::WritePng(
                    absl::StrFormat("%s/FinalImage_%04d.png", Path("gray/FinalImage"), f), gray)
                    .ok());
    absl::StatusOr<double> psnr = fd::client::Psnr(Unit(gray), Unit(Read(GroundTruth(f))));
    ASSERT_TRUE(psnr.ok()) << psnr.status();
    expected_psnr += *psnr / kFrames;
  }
  ReportOptions options;
  options.sequence = Seq();
  options.variants = {{"gray", Path("gray")}};
  options.out_dir = Path("report");
  options.window = 2;
  options.contact_rows = 2;
  ASSERT_TRUE(WriteReport(options).ok());
  std::ifstream in(Path("report/metrics.json"));
  const nlohmann::json metrics = nlohmann::json::parse(in);
  ASSERT_EQ(metrics.at("variants").size(), 1u);
  const nlohmann::json& gray = metrics.at("variants")[0].at("vs_ground_truth");
  EXPECT_NEAR(gray.at("mean_psnr").get<double>(), expected_psnr, 1e-6);
  EXPECT_EQ(gray.at("psnr").size(), static_cast<size_t>(kFrames));
  EXPECT_TRUE(gray.contains("first_window_mean_psnr"));  // 4 frames >= 2 windows of 2
  EXPECT_GE(gray.at("mean_block8_psnr").get<double>(), gray.at("mean_psnr").get<double>());
  // A constant prediction never changes: its flicker error is the ground
  // truth's own frame change.
  EXPECT_NEAR(metrics.at("variants")[0].at("flicker_error").get<double>(),
              metrics.at("ground_truth_frame_change").get<double>(), 1e-9);
  for (const char* file : {"results.md", "per_frame.csv", "stability.png", "contact_sheet.png"}) {
    EXPECT_TRUE(fs::exists(Path("report") + "/" + file)) << file;
  }
  const Image8 sheet = Read(Path("report/contact_sheet.png"));
  EXPECT_GE(sheet.width, 4 * kSize);  // GT | ours | basecolor | irradiance
  EXPECT_GE(sheet.height, 2 * kSize);

  options.variants = {};
  EXPECT_EQ(WriteReport(options).code(), absl::StatusCode::kInvalidArgument);
}

// A prediction that has every 8x8 block's mean right but no texture inside
// the blocks: its block PSNR is near perfect (only uint8 rounding), its
// pixel PSNR is not; and for any prediction averaging can only lower the
// error.
TEST_F(EvaluationTest, BlockPsnrSeparatesTheBlockMeansFromTheTexture) {
  fs::create_directories(Path("blocks/FinalImage"));
  for (int f = 0; f < kFrames; ++f) {
    const Image8 gt = Read(GroundTruth(f));
    Image8 flat(gt.width, gt.height, 3);
    for (int by = 0; by < gt.height; by += 8) {
      for (int bx = 0; bx < gt.width; bx += 8) {
        for (int c = 0; c < 3; ++c) {
          int sum = 0;
          for (int y = by; y < by + 8; ++y) {
            for (int x = bx; x < bx + 8; ++x) sum += gt.at(x, y, c);
          }
          for (int y = by; y < by + 8; ++y) {
            for (int x = bx; x < bx + 8; ++x)
              flat.at(x, y, c) = static_cast<uint8_t>((sum + 32) / 64);
          }
        }
      }
    }
    ASSERT_TRUE(fd::client::WritePng(
                    absl::StrFormat("%s/FinalImage_%04d.png", Path("blocks/FinalImage"), f), flat)
                    .ok());
  }
  ReportOptions options;
  options.sequence = Seq();
  options.variants = {{"blocks", Path("blocks")}};
  options.out_dir = Path("report-blocks");
  options.window = 2;
  options.contact_rows = 1;
  ASSERT_TRUE(WriteReport(options).ok());
  std::ifstream in(Path("report-blocks/metrics.json"));
  const nlohmann::json blocks = nlohmann::json::parse(in).at("variants")[0].at("vs_ground_truth");
  const double block_psnr = blocks.at("mean_block8_psnr").get<double>();
  const double psnr = blocks.at("mean_psnr").get<double>();
  EXPECT_GT(block_psnr, 50.0);  // rounding to uint8 only
  EXPECT_LT(psnr, 40.0);        // the street's texture is gone
}

TEST_F(EvaluationTest, LatentStatisticsHaveOneLinePerChannel) {
  absl::StatusOr<std::string> text = DescribeLatents(Env(), Seq(), 2);
  ASSERT_TRUE(text.ok()) << text.status();
  const std::vector<std::string> lines = absl::StrSplit(*text, '\n', absl::SkipEmpty());
  EXPECT_EQ(lines.size(), 1u + 4u) << *text;  // a header, then the 4 latent channels
  EXPECT_TRUE(absl::StartsWith(lines[1], "channel  0")) << *text;
}

TEST_F(EvaluationTest, DenoisingReportsEachTimestepAndDrawsTheSheet) {
  DenoisingOptions options;
  options.env_dir = Env();
  options.sequence = Seq();
  options.frames = 2;
  options.timesteps = {0, 500, 999};
  options.sheet = Path("denoise.png");
  absl::StatusOr<std::string> text = DescribeDenoising(options);
  ASSERT_TRUE(text.ok()) << text.status();
  const std::vector<std::string> lines = absl::StrSplit(*text, '\n', absl::SkipEmpty());
  ASSERT_EQ(lines.size(), 4u) << *text;
  EXPECT_TRUE(absl::StartsWith(lines[1], "t=  0")) << *text;
  EXPECT_TRUE(absl::StartsWith(lines[3], "t=999")) << *text;
  EXPECT_FALSE(absl::StrContains(*text, "nan")) << *text;
  const Image8 sheet = Read(options.sheet);
  EXPECT_EQ(sheet.width, 4 * kSize);  // round trip + three timesteps
  EXPECT_EQ(sheet.height, 2 * kSize);

  // At t = 0 the noisy latent is the clean one: the x0 estimate is close to
  // the round trip even for random weights (sqrt(1 - a_0) ~ 0.03).
  // At t = 999 it is not.
  auto psnr_of = [&](const std::string& line) {
    const size_t at = line.find("round trip");
    return std::stod(line.substr(at + std::string("round trip").size()));
  };
  EXPECT_GT(psnr_of(lines[1]), psnr_of(lines[3]) + 3.0) << *text;

  options.timesteps = {1000};
  absl::StatusOr<std::string> bad = DescribeDenoising(options);
  EXPECT_EQ(bad.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StrContains(bad.status().message(), "timestep 1000")) << bad.status();
}

}  // namespace
}  // namespace fd::evaluate

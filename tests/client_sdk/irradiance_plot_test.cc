// The irradiance estimate (client_sdk/irradiance.h) and the metric plot
// (client_sdk/plot.h, raster.h).
#include <gtest/gtest.h>

#include <cmath>
#include <limits>

#include "client_sdk/irradiance.h"
#include "client_sdk/plot.h"
#include "client_sdk/raster.h"

namespace fd::client {
namespace {

Image8 Solid(int size, uint8_t r, uint8_t g, uint8_t b) {
  Image8 image(size, size, 3);
  for (size_t p = 0; p < image.pixels.size(); p += 3) {
    image.pixels[p] = r;
    image.pixels[p + 1] = g;
    image.pixels[p + 2] = b;
  }
  return image;
}

TEST(IrradianceTest, FollowsTheReferenceFormula) {
  struct Case {
    uint8_t out, albedo, expected;
  } cases[] = {
      // 0.2 / (0.4 + 1e-6) = 0.4999988 -> / 2 * 255 = 63.75 -> truncated 63.
      {51, 102, 63},
      // Dark albedo (luma 2/255 <= 0.01): 2.0 -> 255.
      {51, 2, 255},
      // Bright output on dim albedo: ratio 5 clamps to 2 -> 255.
      {255, 51, 255},
      {0, 128, 0},
      // Equal luma: ratio just below 1 (the 1e-6) -> 127.49... -> 127.
      {128, 128, 127},
  };
  for (const Case& c : cases) {
    absl::StatusOr<Image8> irradiance =
        IrradianceMap(Solid(4, c.out, c.out, c.out), Solid(4, c.albedo, c.albedo, c.albedo));
    ASSERT_TRUE(irradiance.ok());
    ASSERT_EQ(irradiance->channels, 1);
    EXPECT_EQ(irradiance->pixels[5], c.expected) << int(c.out) << " / " << int(c.albedo);
  }
  // Luma weights 0.299 / 0.587 / 0.114: pure red output 255 -> luma 0.299 on
  // a white albedo (luma 1.0) -> 0.299 / 2 * 255 = 38.1 -> 38.
  absl::StatusOr<Image8> red = IrradianceMap(Solid(2, 255, 0, 0), Solid(2, 255, 255, 255));
  ASSERT_TRUE(red.ok());
  EXPECT_EQ(red->pixels[0], 38);
}

TEST(IrradianceTest, RejectsMismatchedInputs) {
  EXPECT_EQ(IrradianceMap(Solid(4, 1, 1, 1), Solid(5, 1, 1, 1)).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(IrradianceMap(Image8(4, 4, 1), Solid(4, 1, 1, 1)).status().code(),
            absl::StatusCode::kInvalidArgument);
}

int CountColor(const Image8& image, Rgb color, int y0, int y1) {
  int count = 0;
  for (int y = y0; y < y1; ++y) {
    for (int x = 0; x < image.width; ++x) {
      if (image.at(x, y, 0) == color.r && image.at(x, y, 1) == color.g &&
          image.at(x, y, 2) == color.b) {
        ++count;
      }
    }
  }
  return count;
}

TEST(RasterTest, TextDrawsTheGlyphBits) {
  Image8 image(20, 20, 3);
  Canvas canvas(&image);
  canvas.Fill({255, 255, 255});
  canvas.Text(1, 1, "1", {0, 0, 0}, 2);
  // '1' has 10 set bits in its 5x7 glyph; each is a 2x2 square.
  EXPECT_EQ(CountColor(image, {0, 0, 0}, 0, 20), 40);
  EXPECT_EQ(Canvas::TextWidth("10", 2), 22);
}

TEST(PlotTest, DrawsOnePanelPerSeries) {
  std::vector<int64_t> frames;
  std::vector<double> psnr, ssim;
  for (int f = 0; f < 30; ++f) {
    frames.push_back(f);
    psnr.push_back(25.0 + 3.0 * std::sin(f * 0.3));
    ssim.push_back(0.8 + 0.1 * std::cos(f * 0.2));
  }
  psnr[4] = std::numeric_limits<double>::infinity();
  const Rgb blue{31, 119, 180}, orange{255, 127, 14};
  absl::StatusOr<Image8> plot =
      PlotOverFrames(frames, {{"PSNR (dB)", psnr, blue}, {"SSIM", ssim, orange}}, 800, 500);
  ASSERT_TRUE(plot.ok()) << plot.status();
  EXPECT_EQ(plot->width, 800);
  EXPECT_EQ(plot->height, 500);
  EXPECT_EQ(plot->channels, 3);
  // Each series is drawn in its own (top / bottom) half.
  EXPECT_GT(CountColor(*plot, blue, 0, 250), 500);
  EXPECT_EQ(CountColor(*plot, blue, 260, 500), 0);
  EXPECT_GT(CountColor(*plot, orange, 250, 500), 500);
  EXPECT_EQ(CountColor(*plot, orange, 0, 230), 0);
}

TEST(PlotTest, SingleFrameAndErrors) {
  EXPECT_TRUE(PlotOverFrames({7}, {{"SSIM", {0.5}, {0, 0, 0}}}).ok());
  EXPECT_EQ(PlotOverFrames({}, {{"SSIM", {}, {0, 0, 0}}}).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(PlotOverFrames({1, 2}, {{"SSIM", {0.5}, {0, 0, 0}}}).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(PlotOverFrames({1}, {{"SSIM", {0.5}, {0, 0, 0}}}, 100, 100).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST(PlotTest, NiceTickSteps) {
  EXPECT_DOUBLE_EQ(NiceTickStep(10.0, 5), 2.0);
  EXPECT_DOUBLE_EQ(NiceTickStep(100.0, 8), 10.0);
  EXPECT_NEAR(NiceTickStep(0.37, 5), 0.1, 1e-12);
  EXPECT_NEAR(NiceTickStep(0.2, 5), 0.05, 1e-12);
}

}  // namespace
}  // namespace fd::client

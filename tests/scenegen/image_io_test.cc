#include "tools/scenegen/image_io.h"

#include <gtest/gtest.h>

#include <fstream>

#include "tests/scenegen/scenegen_test_util.h"
#include "tools/scenegen/random.h"

namespace fd::scenegen {
namespace {

using testing::FreshDir;
using testing::ReadBytes;

Image8 RandomImage8(int w, int h, int c, uint64_t seed) {
  Image8 image(w, h, c);
  PixelRng rng(seed);
  for (uint8_t& v : image.pixels) v = static_cast<uint8_t>(rng.NextU64() >> 56);
  return image;
}

TEST(ImageIoTest, PngRoundTripsGrayAndRgbExactly) {
  const std::string dir = FreshDir("png_round_trip");
  for (const int channels : {1, 3}) {
    const Image8 image = RandomImage8(37, 21, channels, 7 + channels);
    const std::string path = dir + "/image_" + std::to_string(channels) + ".png";
    ASSERT_TRUE(WritePng(path, image).ok());
    absl::StatusOr<Image8> back = ReadPng(path);
    ASSERT_TRUE(back.ok()) << back.status();
    EXPECT_EQ(back->width, 37);
    EXPECT_EQ(back->height, 21);
    EXPECT_EQ(back->channels, channels);
    EXPECT_EQ(back->pixels, image.pixels);
  }
}

TEST(ImageIoTest, PngBytesDependOnlyOnPixels) {
  const std::string dir = FreshDir("png_bytes");
  const Image8 image = RandomImage8(16, 16, 3, 3);
  ASSERT_TRUE(WritePng(dir + "/a.png", image).ok());
  ASSERT_TRUE(WritePng(dir + "/b.png", image).ok());
  EXPECT_EQ(ReadBytes(dir + "/a.png"), ReadBytes(dir + "/b.png"));
}

TEST(ImageIoTest, WritePngRejectsBadShapes) {
  const std::string dir = FreshDir("png_bad");
  Image8 two_channels(4, 4, 2);
  EXPECT_EQ(WritePng(dir + "/x.png", two_channels).code(), absl::StatusCode::kInvalidArgument);
  Image8 short_buffer(4, 4, 3);
  short_buffer.pixels.pop_back();
  EXPECT_EQ(WritePng(dir + "/x.png", short_buffer).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(WritePng(dir + "/x.png", Image8()).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(WritePng(dir + "/no/such/folder/x.png", Image8(2, 2, 1)).code(),
            absl::StatusCode::kInternal);
}

TEST(ImageIoTest, ReadPngReportsMissingAndCorruptFiles) {
  const std::string dir = FreshDir("png_corrupt");
  EXPECT_EQ(ReadPng(dir + "/missing.png").status().code(), absl::StatusCode::kNotFound);
  std::ofstream(dir + "/garbage.png") << "definitely not a png";
  EXPECT_EQ(ReadPng(dir + "/garbage.png").status().code(), absl::StatusCode::kDataLoss);
}

TEST(ImageIoTest, ExrRoundTripsFloatsExactly) {
  const std::string dir = FreshDir("exr_round_trip");
  for (const int channels : {1, 3}) {
    ImageF image(13, 9, channels);
    PixelRng rng(11 + channels);
    for (float& v : image.pixels) v = rng.Uniform(-2.0f, 50.0f);
    const std::string path = dir + "/image_" + std::to_string(channels) + ".exr";
    ASSERT_TRUE(WriteExr(path, image).ok());
    absl::StatusOr<ImageF> back = ReadExr(path);
    ASSERT_TRUE(back.ok()) << back.status();
    EXPECT_EQ(back->width, 13);
    EXPECT_EQ(back->height, 9);
    EXPECT_EQ(back->channels, channels);
    EXPECT_EQ(back->pixels, image.pixels);
  }
  EXPECT_EQ(ReadExr(dir + "/missing.exr").status().code(), absl::StatusCode::kNotFound);
  std::ofstream(dir + "/garbage.exr") << "not an exr";
  EXPECT_EQ(ReadExr(dir + "/garbage.exr").status().code(), absl::StatusCode::kDataLoss);
}

}  // namespace
}  // namespace fd::scenegen

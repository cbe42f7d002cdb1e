// Image containers and dtype conversions (client_sdk/image.h).
#include "client_sdk/image.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <limits>

namespace fd::client {
namespace {

TEST(HalfTest, ExactValuesRoundTrip) {
  // Values exactly representable in binary16, with their bit patterns.
  const struct {
    float value;
    uint16_t bits;
  } cases[] = {{0.0f, 0x0000},
               {-0.0f, 0x8000},
               {1.0f, 0x3c00},
               {-2.0f, 0xc000},
               {0.5f, 0x3800},
               {65504.0f, 0x7bff},
               {6.103515625e-05f, 0x0400},  // min normal
               {5.9604645e-08f, 0x0001},    // min subnormal 2^-24
               {0.333251953125f, 0x3555}};
  for (const auto& c : cases) {
    EXPECT_EQ(FloatToHalf(c.value).bits, c.bits) << c.value;
    EXPECT_EQ(HalfToFloat(Half{c.bits}), c.value) << c.bits;
  }
}

TEST(HalfTest, RoundsToNearestEvenAndSaturatesToInfinity) {
  // 1 + 2^-11 is exactly halfway between 1 and the next half (1 + 2^-10):
  // ties go to the even mantissa (1.0).
  EXPECT_EQ(FloatToHalf(1.0f + std::ldexp(1.0f, -11)).bits, 0x3c00);
  // 1 + 3 * 2^-11 is halfway between 1 + 2^-10 (odd) and 1 + 2^-9 (even).
  EXPECT_EQ(FloatToHalf(1.0f + 3.0f * std::ldexp(1.0f, -11)).bits, 0x3c02);
  EXPECT_EQ(FloatToHalf(65519.0f).bits, 0x7bff);  // below the halfway point to 65536
  EXPECT_EQ(FloatToHalf(65520.0f).bits, 0x7c00);  // ties to even -> infinity
  EXPECT_EQ(FloatToHalf(1e10f).bits, 0x7c00);
  EXPECT_EQ(FloatToHalf(-std::numeric_limits<float>::infinity()).bits, 0xfc00);
  const Half nan = FloatToHalf(std::numeric_limits<float>::quiet_NaN());
  EXPECT_TRUE(std::isnan(HalfToFloat(nan)));
  // Subnormal rounding: 1.5 * 2^-24 is halfway between 1 and 2 units -> 2.
  EXPECT_EQ(FloatToHalf(1.5f * std::ldexp(1.0f, -24)).bits, 0x0002);
  // Below half a unit rounds to zero.
  EXPECT_EQ(FloatToHalf(0.25f * std::ldexp(1.0f, -24)).bits, 0x0000);
}

TEST(HalfTest, EveryHalfRoundTripsThroughFloat) {
  for (uint32_t bits = 0; bits < 0x10000; ++bits) {
    const Half h{static_cast<uint16_t>(bits)};
    const float f = HalfToFloat(h);
    if (std::isnan(f)) continue;
    ASSERT_EQ(FloatToHalf(f).bits, bits) << std::hex << bits;
  }
}

TEST(ImageTest, Uint8FloatConversions) {
  Image8 image(2, 1, 3);
  image.pixels = {0, 128, 255, 1, 2, 254};
  const ImageF f = ToFloat(ImageView::Of(image));
  ASSERT_EQ(f.pixels.size(), 6u);
  EXPECT_FLOAT_EQ(f.pixels[1], 128.0f / 255.0f);
  EXPECT_EQ(ToUint8(ImageView::Of(f)), image);  // exact round trip

  ImageF odd(3, 1, 1);
  odd.pixels = {-0.5f, 1.5f, std::numeric_limits<float>::quiet_NaN()};
  const Image8 clamped = ToUint8(ImageView::Of(odd));
  EXPECT_EQ(clamped.pixels, (std::vector<uint8_t>{0, 255, 0}));
}

TEST(ImageTest, HalfConversionThroughViews) {
  ImageF f(1, 1, 3);
  f.pixels = {0.25f, 0.5f, 1.0f};
  const ImageF16 h = ToHalf(ImageView::Of(f));
  EXPECT_EQ(h.pixels[0].bits, 0x3400);
  EXPECT_EQ(ToFloat(ImageView::Of(h)), f);
  const AnyImage any = ConvertTo(ImageView::Of(f), DType::kUint8);
  ASSERT_TRUE(std::holds_alternative<Image8>(any));
  EXPECT_EQ(std::get<Image8>(any).pixels, (std::vector<uint8_t>{64, 128, 255}));
}

TEST(ImageTest, ViewHonoursRowStride) {
  // 2x2 gray image stored with 4 bytes per row (2 bytes padding).
  const uint8_t memory[] = {10, 20, 99, 99, 30, 40, 99, 99};
  const ImageView view = ImageView::Raw(memory, 2, 2, 1, DType::kUint8, 4);
  EXPECT_EQ(view.row_stride(), 4u);
  EXPECT_EQ(ToUint8(view).pixels, (std::vector<uint8_t>{10, 20, 30, 40}));
  EXPECT_EQ(ToFloat(view).pixels[3], 40.0f / 255.0f);
}

TEST(ImageTest, ToGrayMatchesPilFixedPoint) {
  Image8 rgb(3, 1, 3);
  rgb.pixels = {255, 0, 0, 0, 255, 0, 10, 200, 30};
  const Image8 gray = ToGray(rgb);
  // PIL: (R*19595 + G*38470 + B*7471 + 0x8000) >> 16.
  EXPECT_EQ(gray.pixels,
            (std::vector<uint8_t>{76, 150, (10 * 19595 + 200 * 38470 + 30 * 7471 + 0x8000) >> 16}));
  Image8 rgba(1, 1, 4);
  rgba.pixels = {1, 2, 3, 4};
  EXPECT_EQ(ToRgb(rgba).pixels, (std::vector<uint8_t>{1, 2, 3}));
  Image8 single(1, 1, 1);
  single.pixels = {7};
  EXPECT_EQ(ToRgb(single).pixels, (std::vector<uint8_t>{7, 7, 7}));
  const AnyImage f = ToChannels(AnyImage(ToFloat(ImageView::Of(rgb))), 1);
  EXPECT_NEAR(std::get<ImageF>(f).pixels[0], 0.299f, 1e-6f);
}

}  // namespace
}  // namespace fd::client

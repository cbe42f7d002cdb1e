#include "server/image_codec.h"

#include <c10/util/Half.h>
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <torch/torch.h>
#include <zstd.h>

#include <cmath>
#include <cstring>
#include <limits>
#include <random>
#include <string>
#include <tuple>
#include <vector>

#include "base/image_buffer.h"
#include "session/pipeline_input_builder.h"

namespace fd::server {
namespace {

using ::testing::HasSubstr;

constexpr char kField[] = "frame.gbuffer.depth";

// Wire images are built here by hand, independently of EncodeImage, so the
// decoder is not tested against itself.
v1::Image MakeImage(uint32_t w, uint32_t h, uint32_t c, v1::DType dtype, std::string data,
                    v1::Compression compression = v1::COMPRESSION_NONE) {
  v1::Image image;
  image.set_width(w);
  image.set_height(h);
  image.set_channels(c);
  image.set_dtype(dtype);
  image.set_compression(compression);
  image.set_data(std::move(data));
  return image;
}

std::string Float32Bytes(const std::vector<float>& values) {
  std::string out(values.size() * 4, '\0');
  for (size_t i = 0; i < values.size(); ++i) {
    uint32_t bits;
    std::memcpy(&bits, &values[i], 4);
    for (int b = 0; b < 4; ++b) out[4 * i + b] = static_cast<char>((bits >> (8 * b)) & 0xFF);
  }
  return out;
}

std::string Float16Bytes(const std::vector<uint16_t>& bits) {
  std::string out(bits.size() * 2, '\0');
  for (size_t i = 0; i < bits.size(); ++i) {
    out[2 * i] = static_cast<char>(bits[i] & 0xFF);
    out[2 * i + 1] = static_cast<char>(bits[i] >> 8);
  }
  return out;
}

// One zstd frame of `raw`, with or without the content size in its header.
std::string Zstd(const std::string& raw, bool content_size = true) {
  ZSTD_CCtx* ctx = ZSTD_createCCtx();
  ZSTD_CCtx_setParameter(ctx, ZSTD_c_compressionLevel, 3);
  ZSTD_CCtx_setParameter(ctx, ZSTD_c_contentSizeFlag, content_size ? 1 : 0);
  std::string out(ZSTD_compressBound(raw.size()), '\0');
  const size_t n = ZSTD_compress2(ctx, out.data(), out.size(), raw.data(), raw.size());
  ZSTD_freeCCtx(ctx);
  EXPECT_FALSE(ZSTD_isError(n));
  out.resize(n);
  const unsigned long long declared = ZSTD_getFrameContentSize(out.data(), out.size());
  if (content_size) {
    EXPECT_EQ(declared, raw.size());
  } else {
    EXPECT_EQ(declared, ZSTD_CONTENTSIZE_UNKNOWN);
  }
  return out;
}

std::string Pattern(size_t n) {
  std::string out(n, '\0');
  for (size_t i = 0; i < n; ++i) out[i] = static_cast<char>((i * 37 + 11) & 0xFF);
  return out;
}

// The decoded elements, for comparisons.
std::vector<uint8_t> Uint8s(const ImageBuffer& image) {
  EXPECT_EQ(image.type(), PixelType::kUint8);
  return {image.uint8_elements().begin(), image.uint8_elements().end()};
}
std::vector<float> Floats(const ImageBuffer& image) {
  EXPECT_EQ(image.type(), PixelType::kFloat32);
  return {image.float_elements().begin(), image.float_elements().end()};
}

// A 3-channel buffer holding `values`.
ImageBuffer Rgb(uint32_t w, uint32_t h, const std::vector<uint8_t>& values) {
  ImageBuffer out(w, h, 3, PixelType::kUint8);
  EXPECT_EQ(values.size(), out.num_elements());
  std::memcpy(out.mutable_data(), values.data(), values.size());
  return out;
}
ImageBuffer Rgb(uint32_t w, uint32_t h, const std::vector<float>& values) {
  ImageBuffer out(w, h, 3, PixelType::kFloat32);
  EXPECT_EQ(values.size(), out.num_elements());
  std::memcpy(out.mutable_floats(), values.data(), values.size() * sizeof(float));
  return out;
}

void ExpectInvalid(const absl::Status& status, const std::string& text) {
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument) << status;
  EXPECT_THAT(std::string(status.message()), HasSubstr(text));
}

// --- Header errors -----------------------------------------------------------

TEST(ImageCodecTest, RejectsWrongWidth) {
  const v1::Image image = MakeImage(64, 2, 1, v1::DTYPE_UINT8, Pattern(128));
  ExpectInvalid(DecodeImage(image, kField, {128, 2, 1}).status(),
                "frame.gbuffer.depth.width: expected 128, got 64");
}

TEST(ImageCodecTest, RejectsWrongHeight) {
  const v1::Image image = MakeImage(4, 3, 1, v1::DTYPE_UINT8, Pattern(12));
  ExpectInvalid(DecodeImage(image, kField, {4, 2, 1}).status(),
                "frame.gbuffer.depth.height: expected 2, got 3");
}

TEST(ImageCodecTest, RejectsRgbaWhereRgbIsExpected) {
  const v1::Image image = MakeImage(4, 2, 4, v1::DTYPE_UINT8, Pattern(32));
  ExpectInvalid(DecodeImage(image, "frame.gbuffer.basecolor", {4, 2, 3}).status(),
                "frame.gbuffer.basecolor.channels: expected 3, got 4");
}

TEST(ImageCodecTest, RejectsUnsetDtype) {
  const v1::Image image = MakeImage(4, 2, 1, v1::DTYPE_UNSPECIFIED, Pattern(8));
  ExpectInvalid(DecodeImage(image, kField, {4, 2, 1}).status(),
                "frame.gbuffer.depth.dtype: must be set");
}

TEST(ImageCodecTest, RejectsUnknownDtype) {
  const v1::Image image = MakeImage(4, 2, 1, static_cast<v1::DType>(7), Pattern(8));
  ExpectInvalid(DecodeImage(image, kField, {4, 2, 1}).status(),
                "frame.gbuffer.depth.dtype: unknown value 7");
}

TEST(ImageCodecTest, RejectsUnknownCompression) {
  const v1::Image image =
      MakeImage(4, 2, 1, v1::DTYPE_UINT8, Pattern(8), static_cast<v1::Compression>(5));
  ExpectInvalid(DecodeImage(image, kField, {4, 2, 1}).status(),
                "frame.gbuffer.depth.compression: unknown value 5");
}

TEST(ImageCodecTest, RejectsWrongByteCount) {
  for (const v1::DType dtype : {v1::DTYPE_UINT8, v1::DTYPE_FLOAT16, v1::DTYPE_FLOAT32}) {
    const size_t element = dtype == v1::DTYPE_UINT8 ? 1 : dtype == v1::DTYPE_FLOAT16 ? 2 : 4;
    const size_t bytes = 4 * 2 * 3 * element;
    const v1::Image image = MakeImage(4, 2, 3, dtype, std::string(bytes - 1, '\0'));
    ExpectInvalid(DecodeImage(image, "frame.sky", {4, 2, 3}).status(),
                  "frame.sky.data: expected " + std::to_string(bytes) + " bytes, got " +
                      std::to_string(bytes - 1));
  }
}

TEST(ImageCodecTest, ByteErrorsAreTheSameForDecodeImageBytes) {
  const v1::Image image = MakeImage(4, 2, 3, v1::DTYPE_UINT8, Pattern(23));
  ExpectInvalid(DecodeImageBytes(image, "open.keyframe", {4, 2, 3}).status(),
                "open.keyframe.data: expected 24 bytes, got 23");
  ExpectInvalid(DecodeImageBytes(image, "open.keyframe", {8, 2, 3}).status(),
                "open.keyframe.width: expected 8, got 4");
}

// --- zstd --------------------------------------------------------------------

TEST(ImageCodecTest, RejectsDataThatIsNotZstd) {
  const v1::Image image =
      MakeImage(4, 2, 1, v1::DTYPE_UINT8, "not a zstd frame", v1::COMPRESSION_ZSTD);
  ExpectInvalid(DecodeImage(image, kField, {4, 2, 1}).status(), "frame.gbuffer.depth.data: zstd");
}

TEST(ImageCodecTest, RejectsEmptyZstdData) {
  const v1::Image image = MakeImage(4, 2, 1, v1::DTYPE_UINT8, "", v1::COMPRESSION_ZSTD);
  ExpectInvalid(DecodeImage(image, kField, {4, 2, 1}).status(), "frame.gbuffer.depth.data: zstd");
}

TEST(ImageCodecTest, RejectsZstdFrameDeclaringTheWrongContentSize) {
  const v1::Image image =
      MakeImage(4, 2, 1, v1::DTYPE_UINT8, Zstd(Pattern(9)), v1::COMPRESSION_ZSTD);
  ExpectInvalid(DecodeImage(image, kField, {4, 2, 1}).status(),
                "frame.gbuffer.depth.data: zstd frame declares 9 bytes, expected 8");
}

TEST(ImageCodecTest, RejectsZipBombByItsHeaderAlone) {
  // A bare frame header declaring 1 TiB and no blocks: decompressing it would
  // fail differently, so the message proves only the header was read.
  std::string header = {'\x28', '\xB5', '\x2F', '\xFD', '\xE0'};  // magic, FHD: 8-byte FCS
  const uint64_t declared = uint64_t{1} << 40;
  for (int b = 0; b < 8; ++b) header.push_back(static_cast<char>((declared >> (8 * b)) & 0xFF));
  ASSERT_EQ(ZSTD_getFrameContentSize(header.data(), header.size()), declared);
  const v1::Image image = MakeImage(4, 2, 1, v1::DTYPE_UINT8, header, v1::COMPRESSION_ZSTD);
  ExpectInvalid(DecodeImage(image, kField, {4, 2, 1}).status(),
                "frame.gbuffer.depth.data: zstd frame declares 1099511627776 bytes, expected 8");
}

TEST(ImageCodecTest, RejectsZstdFrameWithoutContentSizeBeyondTheCap) {
  // 16 MiB of zeros compress to a few hundred bytes; decoding must stop at the
  // expected 8 bytes.
  const std::string bomb = Zstd(std::string(16 << 20, '\0'), /*content_size=*/false);
  ASSERT_LT(bomb.size(), 4096u);
  const v1::Image image = MakeImage(4, 2, 1, v1::DTYPE_UINT8, bomb, v1::COMPRESSION_ZSTD);
  ExpectInvalid(DecodeImage(image, kField, {4, 2, 1}).status(),
                "frame.gbuffer.depth.data: zstd frame decompresses to more than 8 bytes");
  // One byte over the cap is just as bad.
  const v1::Image over =
      MakeImage(4, 2, 1, v1::DTYPE_UINT8, Zstd(Pattern(9), false), v1::COMPRESSION_ZSTD);
  ExpectInvalid(DecodeImageBytes(over, kField, {4, 2, 1}).status(),
                "frame.gbuffer.depth.data: zstd frame decompresses to more than 8 bytes");
}

TEST(ImageCodecTest, RejectsZstdFrameWithoutContentSizeThatIsShort) {
  const v1::Image image =
      MakeImage(4, 2, 1, v1::DTYPE_UINT8, Zstd(Pattern(7), false), v1::COMPRESSION_ZSTD);
  ExpectInvalid(DecodeImage(image, kField, {4, 2, 1}).status(),
                "frame.gbuffer.depth.data: zstd frame holds 7 bytes, expected 8");
}

TEST(ImageCodecTest, AcceptsZstdFrameWithoutContentSizeOfTheRightSize) {
  const std::string raw = Pattern(4 * 2 * 3);
  const v1::Image image =
      MakeImage(4, 2, 3, v1::DTYPE_UINT8, Zstd(raw, false), v1::COMPRESSION_ZSTD);
  absl::StatusOr<ImageBuffer> bytes = DecodeImageBytes(image, kField, {4, 2, 3});
  ASSERT_TRUE(bytes.ok()) << bytes.status();
  const std::vector<uint8_t> elements = Uint8s(*bytes);
  EXPECT_EQ(std::string(elements.begin(), elements.end()), raw);
}

TEST(ImageCodecTest, RejectsTrailingBytesAfterTheZstdFrame) {
  const std::string raw = Pattern(8);
  const v1::Image image =
      MakeImage(4, 2, 1, v1::DTYPE_UINT8, Zstd(raw) + Zstd(raw), v1::COMPRESSION_ZSTD);
  ExpectInvalid(DecodeImage(image, kField, {4, 2, 1}).status(), "frame.gbuffer.depth.data: zstd: ");
}

TEST(ImageCodecTest, RejectsCorruptZstdFrame) {
  std::string frame = Zstd(Pattern(4096));
  frame.resize(frame.size() - 3);  // truncated
  const v1::Image image = MakeImage(64, 64, 1, v1::DTYPE_UINT8, frame, v1::COMPRESSION_ZSTD);
  ExpectInvalid(DecodeImage(image, kField, {64, 64, 1}).status(), "frame.gbuffer.depth.data: zstd");
}

// --- NaN, Inf and clamping ---------------------------------------------------

TEST(ImageCodecTest, RejectsNaNAndInfInFloat32) {
  const float nan = std::numeric_limits<float>::quiet_NaN();
  const float inf = std::numeric_limits<float>::infinity();
  // 3x2 image, 2 channels: element 9 = pixel 4 = (1, 1), channel 1.
  for (const auto& [value, name] :
       {std::pair<float, std::string>{nan, "NaN"}, {inf, "Inf"}, {-inf, "Inf"}}) {
    std::vector<float> values(12, 0.5f);
    values[9] = value;
    const v1::Image image = MakeImage(3, 2, 2, v1::DTYPE_FLOAT32, Float32Bytes(values));
    ExpectInvalid(DecodeImage(image, kField, {3, 2, 2}).status(),
                  "frame.gbuffer.depth.data: " + name + " at pixel (1, 1) channel 1");
    ExpectInvalid(DecodeImageBytes(image, kField, {3, 2, 2}).status(),
                  "frame.gbuffer.depth.data: " + name + " at pixel (1, 1) channel 1");
  }
}

TEST(ImageCodecTest, RejectsNaNAndInfInFloat16) {
  // 3x2 image, 1 channel: element 5 = pixel (2, 1), channel 0.
  for (const auto& [bits, name] : {std::pair<uint16_t, std::string>{0x7E00, "NaN"},
                                   {0xFC01, "NaN"},
                                   {0x7C00, "Inf"},
                                   {0xFC00, "Inf"}}) {
    std::vector<uint16_t> values(6, 0x3800);
    values[5] = bits;
    const v1::Image image = MakeImage(3, 2, 1, v1::DTYPE_FLOAT16, Float16Bytes(values));
    ExpectInvalid(DecodeImage(image, kField, {3, 2, 1}).status(),
                  "frame.gbuffer.depth.data: " + name + " at pixel (2, 1) channel 0");
  }
}

TEST(ImageCodecTest, RejectsNaNInsideZstd) {
  std::vector<float> values(8, 0.25f);
  values[0] = std::numeric_limits<float>::quiet_NaN();
  const v1::Image image =
      MakeImage(4, 2, 1, v1::DTYPE_FLOAT32, Zstd(Float32Bytes(values)), v1::COMPRESSION_ZSTD);
  ExpectInvalid(DecodeImage(image, kField, {4, 2, 1}).status(),
                "frame.gbuffer.depth.data: NaN at pixel (0, 0) channel 0");
}

TEST(ImageCodecTest, ClampsFloat32ToUnitRange) {
  const std::vector<float> values = {-0.5f, 1.5f, 0.25f, -0.0f, 1.0f, 3e38f};
  const v1::Image image = MakeImage(3, 2, 1, v1::DTYPE_FLOAT32, Float32Bytes(values));
  absl::StatusOr<ImageBuffer> t = DecodeImage(image, kField, {3, 2, 1});
  ASSERT_TRUE(t.ok()) << t.status();
  const std::vector<float> p = Floats(*t);
  EXPECT_EQ(p[0], 0.0f);
  EXPECT_EQ(p[1], 1.0f);
  EXPECT_EQ(p[2], 0.25f);
  EXPECT_EQ(p[3], 0.0f);
  EXPECT_FALSE(std::signbit(p[3]));
  EXPECT_EQ(p[4], 1.0f);
  EXPECT_EQ(p[5], 1.0f);
}

TEST(ImageCodecTest, ClampsFloat16RoundingOvershoot) {
  // 0x3C01 = 1.0009765625 (fp16 rounding above 1), 0x8001 = -2^-24,
  // 0xBC00 = -1, 0x7BFF = 65504, 0x3400 = 0.25, 0x0001 = 2^-24 (kept).
  const std::vector<uint16_t> bits = {0x3C01, 0x8001, 0xBC00, 0x7BFF, 0x3400, 0x0001};
  const v1::Image image = MakeImage(2, 3, 1, v1::DTYPE_FLOAT16, Float16Bytes(bits));
  absl::StatusOr<ImageBuffer> t = DecodeImage(image, kField, {2, 3, 1});
  ASSERT_TRUE(t.ok()) << t.status();
  const std::vector<float> p = Floats(*t);
  EXPECT_EQ(p[0], 1.0f);
  EXPECT_EQ(p[1], 0.0f);
  EXPECT_EQ(p[2], 0.0f);
  EXPECT_EQ(p[3], 1.0f);
  EXPECT_EQ(p[4], 0.25f);
  EXPECT_EQ(p[5], std::ldexp(1.0f, -24));
}

// --- fp16 conversion ---------------------------------------------------------

TEST(ImageCodecTest, Float16ConversionIsExact) {
  struct Case {
    float value;
    uint16_t bits;
  };
  const Case cases[] = {
      {0.0f, 0x0000},
      {-0.0f, 0x8000},
      {1.0f, 0x3C00},
      {0.5f, 0x3800},
      {-2.0f, 0xC000},
      {65504.0f, 0x7BFF},                      // largest finite
      {std::ldexp(1.0f, -14), 0x0400},         // smallest normal
      {std::ldexp(1.0f, -24), 0x0001},         // smallest subnormal
      {0.333251953125f, 0x3555},               // fp16(1/3)
      {1.0f + std::ldexp(1.0f, -10), 0x3C01},  // 1 + ulp
  };
  for (const Case& c : cases) {
    EXPECT_EQ(FloatToHalfBits(c.value), c.bits) << c.value;
    const float back = HalfBitsToFloat(c.bits);
    EXPECT_EQ(back, c.value) << c.bits;
    EXPECT_EQ(std::signbit(back), std::signbit(c.value));
  }
}

TEST(ImageCodecTest, Float16RoundsToNearestEven) {
  EXPECT_EQ(FloatToHalfBits(1.0f / 3.0f), 0x3555);
  EXPECT_EQ(FloatToHalfBits(0.1f), 0x2E66);
  // Exactly halfway between 1 and 1 + 2^-10: to the even mantissa (1).
  EXPECT_EQ(FloatToHalfBits(1.0f + std::ldexp(1.0f, -11)), 0x3C00);
  // Halfway between 1 + 2^-10 and 1 + 2^-9: to the even one (1 + 2^-9).
  EXPECT_EQ(FloatToHalfBits(1.0f + 3 * std::ldexp(1.0f, -11)), 0x3C02);
  // Just above halfway rounds up.
  EXPECT_EQ(FloatToHalfBits(std::nextafter(1.0f + std::ldexp(1.0f, -11), 2.0f)), 0x3C01);
  // Overflow and specials.
  EXPECT_EQ(FloatToHalfBits(65520.0f), 0x7C00);
  EXPECT_EQ(FloatToHalfBits(std::numeric_limits<float>::infinity()), 0x7C00);
  EXPECT_EQ(FloatToHalfBits(-std::numeric_limits<float>::infinity()), 0xFC00);
  const uint16_t nan = FloatToHalfBits(std::numeric_limits<float>::quiet_NaN());
  EXPECT_EQ(nan & 0x7C00, 0x7C00);
  EXPECT_NE(nan & 0x03FF, 0);
  // Below half the smallest subnormal: zero; above: the smallest subnormal.
  EXPECT_EQ(FloatToHalfBits(std::ldexp(1.0f, -26)), 0x0000);
  EXPECT_EQ(FloatToHalfBits(std::ldexp(1.5f, -25)), 0x0001);
}

TEST(ImageCodecTest, EncodesFloat16LittleEndian) {
  v1::Image image;
  const std::vector<float> rgb = {1.0f, 0.5f, 0.1f};
  ASSERT_TRUE(EncodeImage(Rgb(1, 1, rgb), session::OutputDType::kFloat16,
                          session::OutputCompression::kNone, &image)
                  .ok());
  EXPECT_EQ(image.data(), std::string("\x00\x3C\x00\x38\x66\x2E", 6));
}

// --- Layout ------------------------------------------------------------------

TEST(ImageCodecTest, DecodesRowMajorHwc) {
  // Element ((y * W) + x) * C + c.
  const uint32_t w = 5, h = 3, c = 3;
  const std::string raw = Pattern(w * h * c);
  absl::StatusOr<ImageBuffer> t =
      DecodeImage(MakeImage(w, h, c, v1::DTYPE_UINT8, raw), "frame.gbuffer.basecolor", {w, h, c});
  ASSERT_TRUE(t.ok()) << t.status();
  EXPECT_EQ(t->type(), PixelType::kUint8);
  EXPECT_EQ(t->width(), w);
  EXPECT_EQ(t->height(), h);
  EXPECT_EQ(t->channels(), c);
  // The HWC view the session builds for the model reads the same elements.
  const torch::Tensor view = session::TensorView(*t);
  EXPECT_EQ(view.sizes(), (std::vector<int64_t>{h, w, c}));
  EXPECT_TRUE(view.is_contiguous());
  for (int64_t y = 0; y < h; ++y) {
    for (int64_t x = 0; x < w; ++x) {
      for (int64_t k = 0; k < c; ++k) {
        EXPECT_EQ(view.index({y, x, k}).item<uint8_t>(),
                  static_cast<uint8_t>(raw[(y * w + x) * c + k]));
      }
    }
  }
}

TEST(ImageCodecTest, DecodesFloatDtypesToFloat32) {
  const std::vector<float> values = {0.0f, 0.25f, 0.5f, 1.0f};
  absl::StatusOr<ImageBuffer> f32 =
      DecodeImage(MakeImage(2, 2, 1, v1::DTYPE_FLOAT32, Float32Bytes(values)), kField, {2, 2, 1});
  absl::StatusOr<ImageBuffer> f16 = DecodeImage(
      MakeImage(2, 2, 1, v1::DTYPE_FLOAT16, Float16Bytes({0x0000, 0x3400, 0x3800, 0x3C00})), kField,
      {2, 2, 1});
  ASSERT_TRUE(f32.ok()) << f32.status();
  ASSERT_TRUE(f16.ok()) << f16.status();
  for (const ImageBuffer& t : {*f32, *f16}) {
    EXPECT_EQ(t.type(), PixelType::kFloat32);
    EXPECT_EQ(session::TensorView(t).sizes(), (std::vector<int64_t>{2, 2, 1}));
    EXPECT_EQ(Floats(t), values);
  }
}

// --- DecodeImageBytes quantisation ----------------------------------------------

TEST(ImageCodecTest, DecodeImageBytesQuantisesFloats) {
  // 0.5 * 255 = 127.5 rounds half to even (128); 0.2 -> 51; clamped ends.
  const std::vector<float> values = {0.0f, 1.0f, 0.5f, 0.2f, -1.0f, 2.0f};
  absl::StatusOr<ImageBuffer> bytes = DecodeImageBytes(
      MakeImage(2, 1, 3, v1::DTYPE_FLOAT32, Float32Bytes(values)), "frame.keyframe", {2, 1, 3});
  ASSERT_TRUE(bytes.ok()) << bytes.status();
  EXPECT_EQ(Uint8s(*bytes), (std::vector<uint8_t>{0, 255, 128, 51, 0, 255}));
}

TEST(ImageCodecTest, DecodeImageBytesMatchesSessionBasecolorBuffer) {
  // The keyframe path and the session's own basecolor quantisation agree.
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> dist(-0.1f, 1.1f);
  const uint32_t w = 16, h = 8;
  std::vector<float> values(w * h * 3);
  for (float& v : values) v = dist(rng);
  const v1::Image image = MakeImage(w, h, 3, v1::DTYPE_FLOAT32, Float32Bytes(values));
  absl::StatusOr<ImageBuffer> bytes = DecodeImageBytes(image, "k", {w, h, 3});
  absl::StatusOr<ImageBuffer> floats = DecodeImage(image, "k", {w, h, 3});
  ASSERT_TRUE(bytes.ok()) << bytes.status();
  ASSERT_TRUE(floats.ok()) << floats.status();
  session::SessionSettings settings;
  settings.width = w;
  settings.height = h;
  absl::StatusOr<ImageBuffer> reference = session::BasecolorBuffer(settings, *floats);
  ASSERT_TRUE(reference.ok()) << reference.status();
  EXPECT_EQ(Uint8s(*bytes), Uint8s(*reference));
}

// --- Round trips ---------------------------------------------------------------

class ImageCodecRoundTripTest : public ::testing::TestWithParam<
                                    std::tuple<session::OutputDType, session::OutputCompression>> {
};

TEST_P(ImageCodecRoundTripTest, EncodeThenDecodeIsIdentity) {
  const auto [dtype, compression] = GetParam();
  const uint32_t w = 24, h = 16;
  const size_t n = size_t{w} * h * 3;
  std::mt19937 rng(1234);
  std::vector<uint8_t> u8(n);
  std::vector<float> f(n);
  for (size_t i = 0; i < n; ++i) {
    u8[i] = static_cast<uint8_t>(rng() & 0xFF);
    // Smooth plus noise, so zstd has something to do; arbitrary float32
    // values (fp16 rounds them, compared below).
    f[i] = std::uniform_real_distribution<float>(0.0f, 1.0f)(rng);
  }
  v1::Image image;
  const ImageBuffer rendered = dtype == session::OutputDType::kUint8 ? Rgb(w, h, u8) : Rgb(w, h, f);
  ASSERT_TRUE(EncodeImage(rendered, dtype, compression, &image).ok());
  EXPECT_EQ(image.width(), w);
  EXPECT_EQ(image.height(), h);
  EXPECT_EQ(image.channels(), 3u);
  EXPECT_EQ(static_cast<int>(image.dtype()), static_cast<int>(dtype));
  EXPECT_EQ(static_cast<int>(image.compression()), static_cast<int>(compression));
  const size_t element = dtype == session::OutputDType::kUint8     ? 1
                         : dtype == session::OutputDType::kFloat16 ? 2
                                                                   : 4;
  if (compression == session::OutputCompression::kZstd) {
    EXPECT_EQ(ZSTD_getFrameContentSize(image.data().data(), image.data().size()), n * element);
  } else {
    EXPECT_EQ(image.data().size(), n * element);
  }

  absl::StatusOr<ImageBuffer> t = DecodeImage(image, "frame", {w, h, 3});
  ASSERT_TRUE(t.ok()) << t.status();
  EXPECT_EQ(session::TensorView(*t).sizes(), (std::vector<int64_t>{h, w, 3}));
  if (dtype == session::OutputDType::kUint8) {
    ASSERT_EQ(t->type(), PixelType::kUint8);
    EXPECT_EQ(Uint8s(*t), u8);
    absl::StatusOr<ImageBuffer> bytes = DecodeImageBytes(image, "frame", {w, h, 3});
    ASSERT_TRUE(bytes.ok()) << bytes.status();
    EXPECT_EQ(Uint8s(*bytes), u8);
    return;
  }
  ASSERT_EQ(t->type(), PixelType::kFloat32);
  const std::vector<float> p = Floats(*t);
  for (size_t i = 0; i < n; ++i) {
    const float want =
        dtype == session::OutputDType::kFloat32 ? f[i] : HalfBitsToFloat(FloatToHalfBits(f[i]));
    ASSERT_EQ(p[i], want) << i;
  }
}

TEST(ImageCodecTest, Float16RepresentableValuesSurviveExactly) {
  // k / 1024 is exact in binary16 and binary32.
  std::vector<float> f(8 * 4 * 3);
  for (size_t i = 0; i < f.size(); ++i) f[i] = static_cast<float>(i * 11 % 1025) / 1024.0f;
  for (const session::OutputDType dtype :
       {session::OutputDType::kFloat16, session::OutputDType::kFloat32}) {
    for (const session::OutputCompression compression :
         {session::OutputCompression::kNone, session::OutputCompression::kZstd}) {
      v1::Image image;
      ASSERT_TRUE(EncodeImage(Rgb(8, 4, f), dtype, compression, &image).ok());
      absl::StatusOr<ImageBuffer> t = DecodeImage(image, "frame", {8, 4, 3});
      ASSERT_TRUE(t.ok()) << t.status();
      EXPECT_EQ(Floats(*t), f);
    }
  }
}

INSTANTIATE_TEST_SUITE_P(AllDtypesAndCompressions, ImageCodecRoundTripTest,
                         ::testing::Combine(::testing::Values(session::OutputDType::kUint8,
                                                              session::OutputDType::kFloat16,
                                                              session::OutputDType::kFloat32),
                                            ::testing::Values(session::OutputCompression::kNone,
                                                              session::OutputCompression::kZstd)));

// --- EncodeImage errors --------------------------------------------------------

// (An ImageBuffer always holds width x height x channels elements, so the
// old "span of the wrong size" errors cannot happen; what can be wrong is
// the channel count, the element type for the dtype, or an empty image.)
TEST(ImageCodecTest, EncodeRejectsWrongImagesAndLeavesOutputAlone) {
  v1::Image image;
  image.set_width(99);
  const ImageBuffer two_channels(4, 2, 2, PixelType::kUint8);
  ExpectInvalid(EncodeImage(two_channels, session::OutputDType::kUint8,
                            session::OutputCompression::kNone, &image),
                "expected 3 channels, got 2");
  const ImageBuffer floats(4, 2, 3, PixelType::kFloat32);
  const ImageBuffer bytes(4, 2, 3, PixelType::kUint8);
  ExpectInvalid(
      EncodeImage(floats, session::OutputDType::kUint8, session::OutputCompression::kNone, &image),
      "uint8_rgb: expected 24 values, got 0");
  ExpectInvalid(
      EncodeImage(bytes, session::OutputDType::kFloat16, session::OutputCompression::kZstd, &image),
      "float_rgb: expected 24 values, got 0");
  ExpectInvalid(
      EncodeImage(bytes, session::OutputDType::kFloat32, session::OutputCompression::kNone, &image),
      "float_rgb: expected 24 values, got 0");
  ExpectInvalid(EncodeImage(ImageBuffer(), session::OutputDType::kUint8,
                            session::OutputCompression::kNone, &image),
                "width and height must be > 0");
  EXPECT_EQ(image.width(), 99u);
  EXPECT_TRUE(image.data().empty());
}

TEST(ImageCodecTest, EncodeWritesTheImageAsIs) {
  v1::Image image;
  ASSERT_TRUE(EncodeImage(Rgb(2, 2, std::vector<uint8_t>(2 * 2 * 3, 7)),
                          session::OutputDType::kUint8, session::OutputCompression::kNone, &image)
                  .ok());
  EXPECT_EQ(image.data(), std::string(12, '\x07'));
}

// The codec's own binary16 conversion (no LibTorch in the codec) agrees
// with LibTorch's c10::Half on every half value and on a sweep of floats.
TEST(ImageCodecTest, Float16ConversionMatchesLibTorchEverywhere) {
  for (uint32_t bits = 0; bits <= 0xFFFF; ++bits) {
    const float mine = HalfBitsToFloat(static_cast<uint16_t>(bits));
    const float torch_value =
        static_cast<float>(c10::Half(static_cast<uint16_t>(bits), c10::Half::from_bits()));
    if (std::isnan(torch_value)) {
      ASSERT_TRUE(std::isnan(mine)) << bits;
    } else {
      ASSERT_EQ(std::memcmp(&mine, &torch_value, sizeof(float)), 0) << bits;
    }
  }
  // Every 997th float bit pattern (both signs, all exponents) plus the
  // halfway and boundary cases around each half value near 1 and 2^-14.
  std::vector<float> floats;
  for (uint64_t f = 0; f <= 0xFFFFFFFFull; f += 997) {
    float value;
    const uint32_t bits = static_cast<uint32_t>(f);
    std::memcpy(&value, &bits, sizeof(value));
    floats.push_back(value);
  }
  for (uint32_t half = 0; half < 0x7C00; half += 7) {
    const float a = HalfBitsToFloat(static_cast<uint16_t>(half));
    const float b = HalfBitsToFloat(static_cast<uint16_t>(half + 1));
    const float mid = a + (b - a) / 2;
    floats.insert(floats.end(), {mid, std::nextafter(mid, 0.0f), std::nextafter(mid, 1e9f), -mid});
  }
  for (const float value : floats) {
    const uint16_t torch_bits = c10::Half(value).x;
    const uint16_t mine = FloatToHalfBits(value);
    if (std::isnan(value)) {
      ASSERT_EQ(mine & 0x7C00, 0x7C00);
      ASSERT_NE(mine & 0x03FF, 0);
    } else {
      ASSERT_EQ(mine, torch_bits) << value;
    }
  }
}

}  // namespace
}  // namespace fd::server

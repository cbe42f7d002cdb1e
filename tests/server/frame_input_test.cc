#include "server/frame_input.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <cstring>
#include <limits>
#include <string>
#include <vector>

#include "session/pipeline_input_builder.h"

namespace fd::server {
namespace {

using ::testing::HasSubstr;

// A decoded image's bytes, for comparisons.
std::vector<uint8_t> Bytes(const ImageBuffer& image) {
  return {image.bytes().begin(), image.bytes().end()};
}

// Non-square, so a swapped width/height shows.
constexpr uint32_t kWidth = 16;
constexpr uint32_t kHeight = 8;

v1::Image U8Image(uint32_t channels, uint8_t fill, uint32_t w = kWidth, uint32_t h = kHeight) {
  v1::Image image;
  image.set_width(w);
  image.set_height(h);
  image.set_channels(channels);
  image.set_dtype(v1::DTYPE_UINT8);
  image.set_data(std::string(size_t{w} * h * channels, static_cast<char>(fill)));
  return image;
}

v1::Image F32Image(uint32_t channels, float fill) {
  v1::Image image;
  image.set_width(kWidth);
  image.set_height(kHeight);
  image.set_channels(channels);
  image.set_dtype(v1::DTYPE_FLOAT32);
  std::string data(size_t{kWidth} * kHeight * channels * 4, '\0');
  for (size_t i = 0; i < data.size(); i += 4) std::memcpy(&data[i], &fill, 4);
  image.set_data(std::move(data));
  return image;
}

void ExpectInvalid(const absl::Status& status, const std::string& text) {
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument) << status;
  EXPECT_THAT(std::string(status.message()), HasSubstr(text));
}

class FrameInputTest : public ::testing::Test {
 protected:
  FrameInputTest() {
    settings_.environment = "test";
    settings_.width = kWidth;
    settings_.height = kHeight;
    settings_.steps = 1;
    settings_.sky_mode = session::SkyMode::kOff;
    frame_.set_frame_index(3);
    v1::GBuffer* g = frame_.mutable_gbuffer();
    *g->mutable_basecolor() = U8Image(3, 10);
    *g->mutable_normals() = U8Image(3, 128);
    *g->mutable_depth() = F32Image(1, 0.5f);
    *g->mutable_roughness() = U8Image(1, 200);
  }

  session::SessionSettings settings_;
  v1::FrameInput frame_;
};

TEST_F(FrameInputTest, DecodesAValidFrame) {
  absl::StatusOr<DecodedFrame> decoded = DecodeFrameInput(frame_, settings_);
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  const session::FrameGBuffer& g = decoded->gbuffer;
  EXPECT_EQ(session::TensorView(g.basecolor).sizes(), (std::vector<int64_t>{kHeight, kWidth, 3}));
  EXPECT_EQ(session::TensorView(g.basecolor).scalar_type(), torch::kUInt8);
  EXPECT_EQ(session::TensorView(g.normals).sizes(), (std::vector<int64_t>{kHeight, kWidth, 3}));
  EXPECT_EQ(session::TensorView(g.depth).sizes(), (std::vector<int64_t>{kHeight, kWidth, 1}));
  EXPECT_EQ(session::TensorView(g.depth).scalar_type(), torch::kFloat32);
  EXPECT_EQ(session::TensorView(g.depth).index({0, 0, 0}).item<float>(), 0.5f);
  EXPECT_EQ(session::TensorView(g.roughness).sizes(), (std::vector<int64_t>{kHeight, kWidth, 1}));
  EXPECT_EQ(session::TensorView(g.roughness)
                .index({int64_t{kHeight} - 1, int64_t{kWidth} - 1, 0})
                .item<uint8_t>(),
            200);
  EXPECT_TRUE(g.metallic.empty());
  EXPECT_TRUE(g.sky.empty());
  EXPECT_FALSE(decoded->reseed.has_value());
}

TEST_F(FrameInputTest, DecodesOptionalMetallic) {
  *frame_.mutable_gbuffer()->mutable_metallic() = U8Image(1, 255);
  absl::StatusOr<DecodedFrame> decoded = DecodeFrameInput(frame_, settings_);
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  ASSERT_FALSE(decoded->gbuffer.metallic.empty());
  EXPECT_EQ(session::TensorView(decoded->gbuffer.metallic).sizes(),
            (std::vector<int64_t>{kHeight, kWidth, 1}));
}

TEST_F(FrameInputTest, RequiresTheGBuffer) {
  frame_.clear_gbuffer();
  ExpectInvalid(DecodeFrameInput(frame_, settings_).status(), "frame.gbuffer: required");
}

TEST_F(FrameInputTest, RequiresEveryPlaneButMetallic) {
  const struct {
    void (v1::GBuffer::*clear)();
    std::string field;
  } planes[] = {
      {&v1::GBuffer::clear_basecolor, "frame.gbuffer.basecolor"},
      {&v1::GBuffer::clear_normals, "frame.gbuffer.normals"},
      {&v1::GBuffer::clear_depth, "frame.gbuffer.depth"},
      {&v1::GBuffer::clear_roughness, "frame.gbuffer.roughness"},
  };
  for (const auto& plane : planes) {
    v1::FrameInput frame = frame_;
    (frame.mutable_gbuffer()->*plane.clear)();
    ExpectInvalid(DecodeFrameInput(frame, settings_).status(), plane.field + ": required");
  }
}

TEST_F(FrameInputTest, ChecksChannelsPerPlane) {
  *frame_.mutable_gbuffer()->mutable_normals() = U8Image(1, 0);
  ExpectInvalid(DecodeFrameInput(frame_, settings_).status(),
                "frame.gbuffer.normals.channels: expected 3, got 1");
  frame_.mutable_gbuffer()->mutable_normals()->CopyFrom(U8Image(3, 0));
  *frame_.mutable_gbuffer()->mutable_depth() = U8Image(3, 0);
  ExpectInvalid(DecodeFrameInput(frame_, settings_).status(),
                "frame.gbuffer.depth.channels: expected 1, got 3");
  *frame_.mutable_gbuffer()->mutable_depth() = U8Image(1, 0);
  *frame_.mutable_gbuffer()->mutable_metallic() = U8Image(3, 0);
  ExpectInvalid(DecodeFrameInput(frame_, settings_).status(),
                "frame.gbuffer.metallic.channels: expected 1, got 3");
}

TEST_F(FrameInputTest, ChecksTheSessionSize) {
  *frame_.mutable_gbuffer()->mutable_metallic() = U8Image(1, 0, kHeight, kWidth);  // swapped
  ExpectInvalid(DecodeFrameInput(frame_, settings_).status(),
                "frame.gbuffer.metallic.width: expected 16, got 8");
  *frame_.mutable_gbuffer()->mutable_metallic() = U8Image(1, 0, kWidth, kHeight + 8);
  ExpectInvalid(DecodeFrameInput(frame_, settings_).status(),
                "frame.gbuffer.metallic.height: expected 8, got 16");
}

TEST_F(FrameInputTest, NamesTheFieldOfDataErrors) {
  *frame_.mutable_gbuffer()->mutable_roughness() =
      F32Image(1, std::numeric_limits<float>::quiet_NaN());
  ExpectInvalid(DecodeFrameInput(frame_, settings_).status(),
                "frame.gbuffer.roughness.data: NaN at pixel (0, 0) channel 0");
  *frame_.mutable_gbuffer()->mutable_roughness() = U8Image(1, 0);
  frame_.mutable_gbuffer()->mutable_basecolor()->set_dtype(v1::DTYPE_UNSPECIFIED);
  ExpectInvalid(DecodeFrameInput(frame_, settings_).status(),
                "frame.gbuffer.basecolor.dtype: must be set");
}

TEST_F(FrameInputTest, RequiresTheSkyImageInClientImageMode) {
  settings_.sky_mode = session::SkyMode::kClientImage;
  ExpectInvalid(DecodeFrameInput(frame_, settings_).status(),
                "frame.sky: required in sky mode client_image");
  *frame_.mutable_sky() = U8Image(1, 0);
  ExpectInvalid(DecodeFrameInput(frame_, settings_).status(),
                "frame.sky.channels: expected 3, got 1");
  *frame_.mutable_sky() = F32Image(3, 0.75f);
  absl::StatusOr<DecodedFrame> decoded = DecodeFrameInput(frame_, settings_);
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  ASSERT_FALSE(decoded->gbuffer.sky.empty());
  EXPECT_EQ(session::TensorView(decoded->gbuffer.sky).sizes(),
            (std::vector<int64_t>{kHeight, kWidth, 3}));
}

TEST_F(FrameInputTest, IgnoresTheSkyImageInOtherModes) {
  *frame_.mutable_sky() = U8Image(1, 0);  // would be invalid in client_image mode
  for (const session::SkyMode mode : {session::SkyMode::kOff, session::SkyMode::kPreviousOutput}) {
    settings_.sky_mode = mode;
    absl::StatusOr<DecodedFrame> decoded = DecodeFrameInput(frame_, settings_);
    ASSERT_TRUE(decoded.ok()) << decoded.status();
    EXPECT_TRUE(decoded->gbuffer.sky.empty());
  }
}

TEST_F(FrameInputTest, DecodesTheReseedKeyframeAsBytes) {
  *frame_.mutable_keyframe() = F32Image(3, 1.0f);
  absl::StatusOr<DecodedFrame> decoded = DecodeFrameInput(frame_, settings_);
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  ASSERT_TRUE(decoded->reseed.has_value());
  EXPECT_EQ(Bytes(decoded->reseed->frame), std::vector<uint8_t>(kWidth * kHeight * 3, 255));
  EXPECT_TRUE(decoded->reseed->basecolor.empty());  // this frame's basecolor

  *frame_.mutable_keyframe_basecolor() = U8Image(3, 42);
  decoded = DecodeFrameInput(frame_, settings_);
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  ASSERT_TRUE(decoded->reseed.has_value());
  EXPECT_EQ(Bytes(decoded->reseed->basecolor), std::vector<uint8_t>(kWidth * kHeight * 3, 42));
}

TEST_F(FrameInputTest, RejectsKeyframeBasecolorWithoutKeyframe) {
  *frame_.mutable_keyframe_basecolor() = U8Image(3, 42);
  ExpectInvalid(DecodeFrameInput(frame_, settings_).status(),
                "frame.keyframe_basecolor: needs frame.keyframe");
}

TEST_F(FrameInputTest, NamesTheKeyframeFields) {
  *frame_.mutable_keyframe() = U8Image(3, 0, kWidth, kHeight / 2);
  ExpectInvalid(DecodeFrameInput(frame_, settings_).status(),
                "frame.keyframe.height: expected 8, got 4");
  *frame_.mutable_keyframe() = U8Image(3, 0);
  *frame_.mutable_keyframe_basecolor() = U8Image(4, 0);
  ExpectInvalid(DecodeFrameInput(frame_, settings_).status(),
                "frame.keyframe_basecolor.channels: expected 3, got 4");
}

// --- OpenSession keyframe --------------------------------------------------------

TEST(DecodeOpenKeyframeTest, NoKeyframeIsNullopt) {
  v1::OpenSession open;
  absl::StatusOr<std::optional<DecodedStartKeyframe>> keyframe =
      DecodeOpenKeyframe(open, kWidth, kHeight);
  ASSERT_TRUE(keyframe.ok()) << keyframe.status();
  EXPECT_FALSE(keyframe->has_value());
}

TEST(DecodeOpenKeyframeTest, DecodesKeyframeAndBasecolor) {
  v1::OpenSession open;
  *open.mutable_keyframe() = U8Image(3, 9);
  absl::StatusOr<std::optional<DecodedStartKeyframe>> keyframe =
      DecodeOpenKeyframe(open, kWidth, kHeight);
  ASSERT_TRUE(keyframe.ok()) << keyframe.status();
  ASSERT_TRUE(keyframe->has_value());
  EXPECT_EQ(Bytes((*keyframe)->frame), std::vector<uint8_t>(kWidth * kHeight * 3, 9));
  EXPECT_TRUE((*keyframe)->basecolor.empty());

  *open.mutable_keyframe_basecolor() = F32Image(3, 0.0f);
  keyframe = DecodeOpenKeyframe(open, kWidth, kHeight);
  ASSERT_TRUE(keyframe.ok()) << keyframe.status();
  ASSERT_TRUE(keyframe->has_value());
  EXPECT_EQ(Bytes((*keyframe)->basecolor), std::vector<uint8_t>(kWidth * kHeight * 3, 0));
}

TEST(DecodeOpenKeyframeTest, RejectsBasecolorWithoutKeyframe) {
  v1::OpenSession open;
  *open.mutable_keyframe_basecolor() = U8Image(3, 9);
  ExpectInvalid(DecodeOpenKeyframe(open, kWidth, kHeight).status(),
                "open.keyframe_basecolor: needs open.keyframe");
}

TEST(DecodeOpenKeyframeTest, NamesTheOpenFields) {
  v1::OpenSession open;
  *open.mutable_keyframe() = U8Image(3, 9);
  ExpectInvalid(DecodeOpenKeyframe(open, kWidth * 2, kHeight).status(),
                "open.keyframe.width: expected 32, got 16");
  *open.mutable_keyframe_basecolor() = U8Image(1, 9);
  ExpectInvalid(DecodeOpenKeyframe(open, kWidth, kHeight).status(),
                "open.keyframe_basecolor.channels: expected 3, got 1");
}

}  // namespace
}  // namespace fd::server

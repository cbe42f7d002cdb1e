#include "tools/scenegen/encoding.h"

#include <gtest/gtest.h>

#include <cmath>

namespace fd::scenegen {
namespace {

TEST(EncodingTest, DepthIsInverseWithZeroForSkyAndAFarClamp) {
  const float near = 2.0f;
  EXPECT_EQ(EncodeDepth(0.0f, near), 0);  // no geometry
  EXPECT_EQ(EncodeDepth(near, near), 255);
  EXPECT_EQ(EncodeDepth(0.5f * near, near), 255);  // nearer than the near plane saturates
  EXPECT_EQ(EncodeDepth(2.0f * near, near), 128);  // round(255 / 2)
  EXPECT_EQ(EncodeDepth(10.0f * near, near), 26);  // round(25.5)
  // Far geometry never reaches the sky test's threshold.
  EXPECT_EQ(EncodeDepth(1000.0f * near, near), kMinGeometryDepthByte);
  EXPECT_GE(kMinGeometryDepthByte, 10);
  // Monotonic: nearer is brighter.
  int previous = 256;
  for (float d = near; d < 100.0f * near; d *= 1.1f) {
    const int byte = EncodeDepth(d, near);
    EXPECT_LE(byte, previous);
    previous = byte;
  }
}

TEST(EncodingTest, NormalsMapMinusOneToOneOntoBytes) {
  EXPECT_EQ(EncodeNormalComponent(-1.0f), 0);
  EXPECT_EQ(EncodeNormalComponent(0.0f), 128);
  EXPECT_EQ(EncodeNormalComponent(1.0f), 255);
}

TEST(EncodingTest, ToneMapAndSrgbAreMonotonicAndBounded) {
  EXPECT_EQ(ToneMapAces(0.0f), 0.0f);
  EXPECT_LT(ToneMapAces(1000.0f), 1.0001f);
  EXPECT_NEAR(LinearToSrgb(0.5f), 0.7354f, 1e-3f);
  EXPECT_NEAR(LinearToSrgb(1.0f), 1.0f, 1e-6f);
  float previous = -1.0f;
  for (float x = 0.0f; x < 20.0f; x += 0.05f) {
    const float v = LinearToSrgb(ToneMapAces(x));
    EXPECT_GE(v, previous);
    previous = v;
  }
}

// Sky pixels encode to zero in every G-buffer; FinalImage shows the sky.
TEST(EncodingTest, SkyPixelsAreBlackInEveryGBuffer) {
  FrameBuffers b;
  b.width = 2;
  b.height = 1;
  b.geometry = {0, 1};
  b.radiance = {Vec3(0.3f, 0.5f, 0.9f), Vec3(0.2f, 0.2f, 0.2f)};
  b.base_color = {Vec3(), Vec3(0.01f, 0.01f, 0.01f)};  // a very dark material
  b.normal = {Vec3(), Vec3(0, 0, 1)};
  b.view_depth = {0.0f, 5000.0f};  // and very far away
  b.roughness = {0.0f, 0.5f};
  b.metallic = {0.0f, 1.0f};
  const EncodedFrame e = EncodeFrame(b, {1.0f, 1.0f});
  for (int k = 1; k < kNumBuffers; ++k) {
    for (int c = 0; c < e[k].channels; ++c) EXPECT_EQ(e[k].at(0, 0, c), 0) << kBufferNames[k];
  }
  EXPECT_GT(e[static_cast<int>(Buffer::kFinalImage)].at(0, 0, 2), 100);
  // The dark, far surface still fails the sky test through its depth.
  EXPECT_GE(e[static_cast<int>(Buffer::kDepth)].at(1, 0, 0), 10);
  EXPECT_EQ(e[static_cast<int>(Buffer::kNormals)].at(1, 0, 2), 255);
  EXPECT_EQ(e[static_cast<int>(Buffer::kMetallic)].at(1, 0, 0), 255);
  EXPECT_EQ(e[static_cast<int>(Buffer::kRoughness)].at(1, 0, 0), 128);
}

}  // namespace
}  // namespace fd::scenegen

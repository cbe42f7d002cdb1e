// base/image_buffer.h: shared, immutable pixels.
#include "base/image_buffer.h"

#include <gtest/gtest.h>

#include <memory>

namespace fd {
namespace {

TEST(ImageBufferTest, EmptyByDefault) {
  const ImageBuffer image;
  EXPECT_TRUE(image.empty());
  EXPECT_TRUE(image.bytes().empty());
  EXPECT_EQ(image, ImageBuffer());
}

TEST(ImageBufferTest, SizedBufferIsZeroFilledAndWritableUntilShared) {
  ImageBuffer image(4, 2, 3, PixelType::kFloat32);
  EXPECT_EQ(image.num_elements(), 24u);
  EXPECT_EQ(image.size_bytes(), 96u);
  for (float v : image.float_elements()) EXPECT_EQ(v, 0.0f);
  ASSERT_NE(image.mutable_floats(), nullptr);
  image.mutable_floats()[5] = 0.5f;
  const ImageBuffer shared = image;  // copies share the bytes
  EXPECT_EQ(shared.data(), image.data());
  EXPECT_EQ(shared.float_elements()[5], 0.5f);
  EXPECT_EQ(image.mutable_data(), nullptr);  // no writes once shared
}

TEST(ImageBufferTest, WrapSharesForeignBytesAndKeepsThemAlive) {
  auto bytes = std::make_shared<std::vector<uint8_t>>(2 * 2 * 1, 7);
  const uint8_t* data = bytes->data();
  ImageBuffer image = ImageBuffer::Wrap(2, 2, 1, PixelType::kUint8, data, bytes);
  bytes.reset();  // the buffer holds the owner
  EXPECT_EQ(image.data(), data);
  EXPECT_EQ(image.uint8_elements()[3], 7);
  EXPECT_EQ(image.mutable_data(), nullptr);  // wrapped bytes are never written
}

TEST(ImageBufferTest, EqualityIsShapeTypeAndBytes) {
  ImageBuffer a(2, 1, 3, PixelType::kUint8);
  ImageBuffer b(2, 1, 3, PixelType::kUint8);
  EXPECT_EQ(a, b);
  b.mutable_data()[0] = 1;
  EXPECT_NE(a, b);
  EXPECT_NE(ImageBuffer(2, 1, 3, PixelType::kUint8), ImageBuffer(1, 2, 3, PixelType::kUint8));
  EXPECT_NE(ImageBuffer(2, 1, 3, PixelType::kUint8), ImageBuffer());
}

}  // namespace
}  // namespace fd

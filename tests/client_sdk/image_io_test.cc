// PNG / JPEG / EXR files (client_sdk/image_io.h).
#include "client_sdk/image_io.h"

#include <OpenEXR/ImfChannelList.h>
#include <OpenEXR/ImfFrameBuffer.h>
#include <OpenEXR/ImfHeader.h>
#include <OpenEXR/ImfOutputFile.h>
#include <gtest/gtest.h>
#include <png.h>
#include <zlib.h>

#include <cstdio>
#include <cstring>
#include <fstream>
#include <iterator>
#include <utility>

#include "tests/client_sdk/test_util.h"

namespace fd::client {
namespace {

using testing::Pattern8;
using testing::PatternF;
using testing::ScratchDir;

std::string ReadBytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}

// Writes an EXR with arbitrary channel names, each filled with `value + i`.
void WriteExrChannels(const std::string& path, int width, int height,
                      const std::vector<std::string>& names,
                      std::vector<std::vector<float>>* planes) {
  Imf::Header header(width, height);
  Imf::FrameBuffer frame_buffer;
  planes->assign(names.size(), std::vector<float>(size_t(width) * height));
  for (size_t i = 0; i < names.size(); ++i) {
    for (size_t p = 0; p < (*planes)[i].size(); ++p) (*planes)[i][p] = float(i) + 0.001f * p;
    header.channels().insert(names[i], Imf::Channel(Imf::FLOAT));
    frame_buffer.insert(names[i],
                        Imf::Slice(Imf::FLOAT, reinterpret_cast<char*>((*planes)[i].data()),
                                   sizeof(float), sizeof(float) * width));
  }
  Imf::OutputFile file(path.c_str(), header);
  file.setFrameBuffer(frame_buffer);
  file.writePixels(height);
}

void WriteBytes(const std::string& path, const std::string& bytes) {
  std::ofstream(path, std::ios::binary) << bytes;
}

// Overwrites the 4 bytes at `offset` with `value` in `endian` order.
void PutUint32(std::string* bytes, size_t offset, uint32_t value, bool big_endian) {
  for (int i = 0; i < 4; ++i) {
    const int shift = big_endian ? 8 * (3 - i) : 8 * i;
    (*bytes)[offset + i] = static_cast<char>((value >> shift) & 0xff);
  }
}

double MaxAbsDiff(const Image8& a, const Image8& b) {
  double worst = 0;
  for (size_t i = 0; i < a.pixels.size(); ++i) {
    worst = std::max(worst, std::abs(double(a.pixels[i]) - double(b.pixels[i])));
  }
  return worst;
}

TEST(PngTest, RoundTripsGrayRgbAndRgba) {
  ScratchDir dir;
  for (int channels : {1, 3, 4}) {
    const Image8 image = Pattern8(13, 7, channels, channels);
    const std::string path = dir / ("image" + std::to_string(channels) + ".png");
    ASSERT_TRUE(WritePng(path, image).ok());
    absl::StatusOr<Image8> read = ReadPng(path);
    ASSERT_TRUE(read.ok()) << read.status();
    if (channels == 4) {
      EXPECT_EQ(*read, ToRgb(image));  // alpha dropped on read
    } else {
      EXPECT_EQ(*read, image);
    }
    absl::StatusOr<ImageFileInfo> info = ReadImageInfo(path);
    ASSERT_TRUE(info.ok());
    EXPECT_EQ(info->width, 13);
    EXPECT_EQ(info->height, 7);
    EXPECT_EQ(info->channels, channels == 1 ? 1 : 3);
  }
}

TEST(PngTest, EqualImagesGiveByteIdenticalFiles) {
  ScratchDir dir;
  const Image8 image = Pattern8(32, 16, 3, 5);
  ASSERT_TRUE(WritePng(dir / "a.png", image).ok());
  ASSERT_TRUE(WritePng(dir / "b.png", Image8(image)).ok());
  const std::string a = ReadBytes(dir / "a.png");
  EXPECT_FALSE(a.empty());
  EXPECT_EQ(a, ReadBytes(dir / "b.png"));
}

TEST(PngTest, SixteenBitFilesAreRescaledWithoutGamma) {
  ScratchDir dir;
  const std::string path = dir / "wide.png";
  std::vector<uint16_t> wide(256);
  for (int v = 0; v < 256; ++v) wide[v] = static_cast<uint16_t>(v * 257);
  png_image png;
  std::memset(&png, 0, sizeof(png));
  png.version = PNG_IMAGE_VERSION;
  png.width = 16;
  png.height = 16;
  png.format = PNG_FORMAT_LINEAR_Y;
  ASSERT_NE(png_image_write_to_file(&png, path.c_str(), 0, wide.data(), 0, nullptr), 0);
  absl::StatusOr<Image8> read = ReadPng(path);
  ASSERT_TRUE(read.ok()) << read.status();
  ASSERT_EQ(read->channels, 1);
  for (int v = 0; v < 256; ++v) ASSERT_EQ(read->pixels[v], v);
}

TEST(PngTest, Errors) {
  ScratchDir dir;
  EXPECT_EQ(ReadPng(dir / "missing.png").status().code(), absl::StatusCode::kNotFound);
  std::ofstream(dir / "junk.png") << "not a png";
  EXPECT_EQ(ReadPng(dir / "junk.png").status().code(), absl::StatusCode::kDataLoss);
  EXPECT_EQ(WritePng(dir / "bad.png", Image8(2, 2, 2)).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(WritePng(dir / "no/such/folder.png", Image8(2, 2, 3)).code(),
            absl::StatusCode::kInternal);
}

// A header may claim any size in a few bytes (found by fuzzing): the reader
// refuses it before allocating anything for it.
TEST(PngTest, AHeaderClaimingAHugeImageIsDataLoss) {
  ScratchDir dir;
  ASSERT_TRUE(WritePng(dir / "small.png", Pattern8(2, 2, 3, 1)).ok());
  std::string bytes = ReadBytes(dir / "small.png");
  // Signature (8), IHDR length (4), "IHDR" (4), width, height, ..., CRC over
  // "IHDR" + 13 data bytes.
  ASSERT_EQ(bytes.substr(12, 4), "IHDR");
  PutUint32(&bytes, 16, 1000000, /*big_endian=*/true);
  PutUint32(&bytes, 20, 1000000, /*big_endian=*/true);
  const uint32_t crc = crc32(0, reinterpret_cast<const Bytef*>(bytes.data() + 12), 4 + 13);
  PutUint32(&bytes, 29, crc, /*big_endian=*/true);
  WriteBytes(dir / "huge.png", bytes);
  for (const absl::Status& status :
       {ReadPng(dir / "huge.png").status(), ReadImageInfo(dir / "huge.png").status()}) {
    EXPECT_EQ(status.code(), absl::StatusCode::kDataLoss) << status;
    EXPECT_NE(status.message().find("1000000 x 1000000 pixels"), std::string::npos) << status;
  }
}

TEST(JpegTest, ReadsRgbAndGray) {
  ScratchDir dir;
  // Smooth content survives JPEG at quality 100 within a few levels.
  Image8 rgb(24, 16, 3);
  for (int y = 0; y < 16; ++y) {
    for (int x = 0; x < 24; ++x) {
      rgb.at(x, y, 0) = static_cast<uint8_t>(x * 8);
      rgb.at(x, y, 1) = static_cast<uint8_t>(y * 12);
      rgb.at(x, y, 2) = 128;
    }
  }
  testing::WriteJpeg(dir / "rgb.jpg", rgb);
  absl::StatusOr<Image8> read = ReadJpeg(dir / "rgb.jpg");
  ASSERT_TRUE(read.ok()) << read.status();
  EXPECT_EQ(read->channels, 3);
  EXPECT_LE(MaxAbsDiff(*read, rgb), 6.0);

  const Image8 gray = ToGray(rgb);
  testing::WriteJpeg(dir / "gray.jpeg", gray);
  absl::StatusOr<AnyImage> any = ReadImage(dir / "gray.jpeg");
  ASSERT_TRUE(any.ok()) << any.status();
  ASSERT_TRUE(std::holds_alternative<Image8>(*any));
  EXPECT_EQ(ChannelsOf(*any), 1);
  EXPECT_LE(MaxAbsDiff(std::get<Image8>(*any), gray), 3.0);

  absl::StatusOr<ImageFileInfo> info = ReadImageInfo(dir / "rgb.jpg");
  ASSERT_TRUE(info.ok());
  EXPECT_EQ(info->width, 24);
  EXPECT_EQ(info->height, 16);
  EXPECT_EQ(info->channels, 3);
}

TEST(JpegTest, Errors) {
  ScratchDir dir;
  EXPECT_EQ(ReadJpeg(dir / "missing.jpg").status().code(), absl::StatusCode::kNotFound);
  std::ofstream(dir / "junk.jpg") << "definitely not a jpeg file";
  absl::StatusOr<Image8> junk = ReadJpeg(dir / "junk.jpg");
  EXPECT_EQ(junk.status().code(), absl::StatusCode::kDataLoss);
  EXPECT_NE(junk.status().message().find("junk.jpg"), std::string::npos);
}

TEST(ExrTest, RoundTripsFloatAndHalf) {
  ScratchDir dir;
  for (int channels : {1, 3}) {
    const ImageF image = PatternF(9, 5, channels, channels);
    const std::string path = dir / ("f" + std::to_string(channels) + ".exr");
    ASSERT_TRUE(WriteExr(path, image).ok());
    absl::StatusOr<ImageF> read = ReadExr(path);
    ASSERT_TRUE(read.ok()) << read.status();
    EXPECT_EQ(*read, image);

    const ImageF16 half = ToHalf(ImageView::Of(image));
    const std::string half_path = dir / ("h" + std::to_string(channels) + ".exr");
    ASSERT_TRUE(WriteExr(half_path, half).ok());
    absl::StatusOr<ImageF> read_half = ReadExr(half_path);
    ASSERT_TRUE(read_half.ok());
    EXPECT_EQ(*read_half, ToFloat(ImageView::Of(half)));
  }
}

TEST(ExrTest, AcceptsXyzAndSingleNamedChannels) {
  ScratchDir dir;
  std::vector<std::vector<float>> planes;
  WriteExrChannels(dir / "xyz.exr", 4, 3, {"X", "Y", "Z"}, &planes);
  absl::StatusOr<ImageF> xyz = ReadExr(dir / "xyz.exr");
  ASSERT_TRUE(xyz.ok()) << xyz.status();
  ASSERT_EQ(xyz->channels, 3);
  EXPECT_EQ(xyz->at(1, 0, 2), planes[2][1]);  // channel order X, Y, Z

  WriteExrChannels(dir / "z.exr", 4, 3, {"Z"}, &planes);
  absl::StatusOr<ImageF> z = ReadExr(dir / "z.exr");
  ASSERT_TRUE(z.ok()) << z.status();
  EXPECT_EQ(z->channels, 1);
  EXPECT_EQ(z->pixels, planes[0]);

  WriteExrChannels(dir / "ab.exr", 4, 3, {"A", "B"}, &planes);
  absl::StatusOr<ImageF> ab = ReadExr(dir / "ab.exr");
  EXPECT_EQ(ab.status().code(), absl::StatusCode::kDataLoss);
  EXPECT_NE(ab.status().message().find("A,B"), std::string::npos) << ab.status();
}

TEST(ExrTest, MultiLayerFiles) {
  ScratchDir dir;
  const ImageF basecolor = PatternF(8, 8, 3, 1);
  const ImageF depth = PatternF(8, 8, 1, 2);
  const std::string path = dir / "frame.exr";
  ASSERT_TRUE(WriteLayeredExr(path, {{"BaseColor", &basecolor}, {"Depth", &depth}}).ok());
  absl::StatusOr<std::vector<std::string>> layers = ListExrLayers(path);
  ASSERT_TRUE(layers.ok());
  EXPECT_EQ(*layers, (std::vector<std::string>{"BaseColor", "Depth"}));
  EXPECT_EQ(*ReadExrLayer(path, "BaseColor"), basecolor);
  EXPECT_EQ(*ReadExrLayer(path, "Depth"), depth);
  absl::StatusOr<ImageF> missing = ReadExrLayer(path, "Normals");
  EXPECT_EQ(missing.status().code(), absl::StatusCode::kNotFound);
  EXPECT_NE(missing.status().message().find("BaseColor, Depth"), std::string::npos);
  // Two layers and no unlayered channels: ReadExr cannot guess.
  EXPECT_EQ(ReadExr(path).status().code(), absl::StatusCode::kDataLoss);

  // A file with exactly one layer reads as that layer.
  ASSERT_TRUE(WriteLayeredExr(dir / "one.exr", {{"Depth", &depth}}).ok());
  EXPECT_EQ(*ReadExr(dir / "one.exr"), depth);

  const ImageF small = PatternF(4, 4, 3, 3);
  EXPECT_EQ(WriteLayeredExr(dir / "bad.exr", {{"A", &basecolor}, {"B", &small}}).code(),
            absl::StatusCode::kInvalidArgument);
}

// OpenEXR addresses pixels by absolute coordinates: a data window that
// does not start at (0, 0) reads into the image's first pixel.
TEST(ExrTest, ADataWindowAwayFromTheOriginIsRead) {
  ScratchDir dir;
  const Imath::Box2i window(Imath::V2i(-5, -3), Imath::V2i(-2, -1));  // 4 x 3
  Imf::Header header(window, window);
  header.channels().insert("Y", Imf::Channel(Imf::FLOAT));
  std::vector<float> plane(12);
  for (size_t i = 0; i < plane.size(); ++i) plane[i] = 0.5f * i;
  Imf::FrameBuffer frame_buffer;
  frame_buffer.insert("Y", Imf::Slice::Make(Imf::FLOAT, plane.data(), window));
  {
    Imf::OutputFile file((dir / "offset.exr").c_str(), header);
    file.setFrameBuffer(frame_buffer);
    file.writePixels(3);
  }
  absl::StatusOr<ImageF> read = ReadExr(dir / "offset.exr");
  ASSERT_TRUE(read.ok()) << read.status();
  EXPECT_EQ(read->width, 4);
  EXPECT_EQ(read->height, 3);
  EXPECT_EQ(read->pixels, plane);
}

// Headers that claim more than the file holds (found by fuzzing: OpenEXR's
// C++ reader allocates what an attribute's size says) are DATA_LOSS, with
// OpenEXRCore's reason, before anything is allocated for them.
TEST(ExrTest, HeadersClaimingHugeSizesAreDataLoss) {
  ScratchDir dir;
  // Magic, version 2, then one unknown attribute that claims 2e9 bytes.
  std::string opaque("\x76\x2f\x31\x01\x02\x00\x00\x00", 8);
  opaque += std::string("foo\0zzz\0", 8);
  opaque += std::string(4, '\0');
  PutUint32(&opaque, opaque.size() - 4, 2000000000, /*big_endian=*/false);
  opaque += std::string("abc\0", 4);
  WriteBytes(dir / "opaque.exr", opaque);

  // A valid file whose data window is made 1,000,000 pixels wide.
  ASSERT_TRUE(WriteExr(dir / "small.exr", PatternF(4, 3, 1, 1)).ok());
  std::string wide = ReadBytes(dir / "small.exr");
  const std::string key("dataWindow\0box2i\0", 17);
  const size_t at = wide.find(key);
  ASSERT_NE(at, std::string::npos);
  // size (4), then min.x, min.y, max.x, max.y.
  PutUint32(&wide, at + key.size() + 4 + 8, 999999, /*big_endian=*/false);
  WriteBytes(dir / "wide.exr", wide);

  const std::pair<std::string, std::string> cases[] = {
      {"opaque.exr", "'foo', type 'zzz': Invalid size 2000000000"},
      {"wide.exr", "width (1000000) too large (max 16384)"}};
  for (const auto& [name, reason] : cases) {
    const std::string path = dir / name;
    for (const absl::Status& status :
         {ReadExr(path).status(), ReadImageInfo(path).status(), ListExrLayers(path).status()}) {
      EXPECT_EQ(status.code(), absl::StatusCode::kDataLoss) << status;
      EXPECT_NE(status.message().find(path), std::string::npos) << status;
      EXPECT_NE(status.message().find(reason), std::string::npos) << status;
    }
  }
}

TEST(AnyFormatTest, DispatchesOnExtension) {
  ScratchDir dir;
  const Image8 image = Pattern8(8, 4, 3, 9);
  ASSERT_TRUE(WriteImage(dir / "a.PNG", AnyImage(image)).ok());
  absl::StatusOr<AnyImage> png = ReadImage(dir / "a.PNG");
  ASSERT_TRUE(png.ok());
  EXPECT_EQ(std::get<Image8>(*png), image);

  ASSERT_TRUE(WriteImage(dir / "a.exr", AnyImage(ToHalf(ImageView::Of(image)))).ok());
  absl::StatusOr<AnyImage> exr = ReadImage(dir / "a.exr");
  ASSERT_TRUE(exr.ok());
  EXPECT_EQ(ToUint8(*exr), image);  // k/255 survives float16 to within rounding

  EXPECT_EQ(ReadImage(dir / "a.tiff").status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(WriteImage(dir / "a.bmp", AnyImage(image)).code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace fd::client

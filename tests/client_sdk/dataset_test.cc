// Reading the authors' dataset layout and its EXR variants
// (client_sdk/dataset.h), including every malformed-input case.
#include "client_sdk/dataset.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>

#include "absl/strings/str_format.h"
#include "client_sdk/image_io.h"
#include "tests/client_sdk/test_util.h"

namespace fd::client {
namespace {

using ::testing::HasSubstr;
using testing::Pattern8;
using testing::PatternF;
using testing::ScratchDir;
namespace fs = std::filesystem;

// Seed of buffer b in frame f, so every image differs.
int Seed(Buffer buffer, int64_t frame) { return static_cast<int>(buffer) * 1000 + int(frame); }

std::string FileName(const std::string& prefix, Buffer buffer, int64_t frame, const char* ext) {
  return absl::StrFormat("%s%s_%04d.%s", prefix.empty() ? "" : prefix + "_", BufferName(buffer),
                         frame, ext);
}

// Writes frames [first, first + count) of the given buffers as 8-bit files.
void WriteSequence(const fs::path& dir, const std::string& prefix, int64_t first, int count,
                   const std::vector<Buffer>& buffers, int size = 16, const char* ext = "png") {
  for (Buffer buffer : buffers) {
    fs::create_directories(dir / BufferName(buffer));
    for (int64_t f = first; f < first + count; ++f) {
      const Image8 image = Pattern8(size, size, BufferChannels(buffer), Seed(buffer, f));
      const fs::path path = dir / BufferName(buffer) / FileName(prefix, buffer, f, ext);
      ASSERT_TRUE(WritePng(path.string(), image).ok());
    }
  }
}

const std::vector<Buffer> kRequired = {Buffer::kBaseColor, Buffer::kNormals, Buffer::kDepth,
                                       Buffer::kRoughness};
const std::vector<Buffer> kAll = {Buffer::kFinalImage, Buffer::kBaseColor, Buffer::kNormals,
                                  Buffer::kDepth,      Buffer::kRoughness, Buffer::kMetallic};

TEST(DatasetTest, SimpleNamingPng) {
  ScratchDir dir;
  WriteSequence(dir.path(), "", 0, 3, kAll);
  absl::StatusOr<Dataset> dataset = Dataset::Open(dir.path().string());
  ASSERT_TRUE(dataset.ok()) << dataset.status();
  ASSERT_EQ(dataset->frames().size(), 3u);
  EXPECT_EQ(dataset->width(), 16);
  EXPECT_EQ(dataset->height(), 16);
  EXPECT_TRUE(dataset->has(Buffer::kMetallic));
  EXPECT_TRUE(dataset->has(Buffer::kFinalImage));
  EXPECT_FALSE(dataset->multi_layer_exr());
  EXPECT_EQ(dataset->Find(2), std::optional<size_t>(2));
  EXPECT_EQ(dataset->Find(7), std::nullopt);

  absl::StatusOr<DatasetFrame> frame = dataset->ReadFrame(1);
  ASSERT_TRUE(frame.ok()) << frame.status();
  EXPECT_EQ(frame->index, 1);
  EXPECT_EQ(std::get<Image8>(frame->basecolor), Pattern8(16, 16, 3, Seed(Buffer::kBaseColor, 1)));
  EXPECT_EQ(std::get<Image8>(frame->depth), Pattern8(16, 16, 1, Seed(Buffer::kDepth, 1)));
  ASSERT_TRUE(frame->metallic.has_value());
  EXPECT_EQ(std::get<Image8>(*frame->metallic), Pattern8(16, 16, 1, Seed(Buffer::kMetallic, 1)));
  ASSERT_TRUE(frame->final_image.has_value());
  EXPECT_EQ(std::get<Image8>(*frame->final_image),
            Pattern8(16, 16, 3, Seed(Buffer::kFinalImage, 1)));
}

TEST(DatasetTest, PrefixNamingMixedPngAndJpgWithoutMetallic) {
  ScratchDir dir;
  WriteSequence(dir.path(), "Seq", 10, 2, {Buffer::kBaseColor, Buffer::kNormals});
  // Depth as gray JPEGs, Roughness as RGB PNGs (a scalar buffer stored in
  // colour is reduced to luma, like PIL's convert("L")).
  fs::create_directories(dir.path() / "Depth");
  fs::create_directories(dir.path() / "Roughness");
  Image8 smooth(16, 16, 1);
  for (int y = 0; y < 16; ++y) {
    for (int x = 0; x < 16; ++x) smooth.at(x, y, 0) = static_cast<uint8_t>(40 + 8 * x + 2 * y);
  }
  for (int64_t f = 10; f < 12; ++f) {
    testing::WriteJpeg((dir.path() / "Depth" / FileName("Seq", Buffer::kDepth, f, "jpg")).string(),
                       smooth);
    ASSERT_TRUE(
        WritePng(
            (dir.path() / "Roughness" / FileName("Seq", Buffer::kRoughness, f, "png")).string(),
            Pattern8(16, 16, 3, Seed(Buffer::kRoughness, f)))
            .ok());
  }
  absl::StatusOr<Dataset> dataset = Dataset::Open(dir.path().string());
  ASSERT_TRUE(dataset.ok()) << dataset.status();
  EXPECT_FALSE(dataset->has(Buffer::kMetallic));
  EXPECT_FALSE(dataset->has(Buffer::kFinalImage));
  ASSERT_EQ(dataset->frames().size(), 2u);
  EXPECT_EQ(dataset->frames()[0].index, 10);
  absl::StatusOr<DatasetFrame> frame = dataset->ReadFrame(0);
  ASSERT_TRUE(frame.ok()) << frame.status();
  EXPECT_FALSE(frame->metallic.has_value());
  const Image8& depth = std::get<Image8>(frame->depth);
  ASSERT_EQ(depth.channels, 1);
  for (size_t i = 0; i < depth.pixels.size(); ++i) {
    ASSERT_NEAR(depth.pixels[i], smooth.pixels[i], 3) << i;  // JPEG quality 100
  }
  EXPECT_EQ(std::get<Image8>(frame->roughness),
            ToGray(Pattern8(16, 16, 3, Seed(Buffer::kRoughness, 10))));
}

TEST(DatasetTest, PrefersPngOverJpgForTheSameFrame) {
  ScratchDir dir;
  WriteSequence(dir.path(), "", 0, 1, {Buffer::kNormals, Buffer::kDepth, Buffer::kRoughness});
  fs::create_directories(dir.path() / "BaseColor");
  const Image8 gray = Pattern8(16, 16, 1, 77);
  ASSERT_TRUE(WritePng(dir / "BaseColor/BaseColor_0000.png", gray).ok());
  testing::WriteJpeg(dir / "BaseColor/BaseColor_0000.jpg", Pattern8(16, 16, 3, 78));
  absl::StatusOr<Dataset> dataset = Dataset::Open(dir.path().string());
  ASSERT_TRUE(dataset.ok()) << dataset.status();
  EXPECT_THAT(dataset->frames()[0].path(Buffer::kBaseColor), ::testing::EndsWith(".png"));
  absl::StatusOr<DatasetFrame> frame = dataset->ReadFrame(0);
  ASSERT_TRUE(frame.ok()) << frame.status();
  EXPECT_EQ(std::get<Image8>(frame->basecolor), ToRgb(gray));  // gray replicated to RGB
}

TEST(DatasetTest, PerBufferExrWithLinearValues) {
  ScratchDir dir;
  for (Buffer buffer : kRequired) {
    fs::create_directories(dir.path() / BufferName(buffer));
    ImageF image(8, 8, BufferChannels(buffer));
    for (float& v : image.pixels) v = buffer == Buffer::kNormals ? -1.0f : 0.5f;
    ASSERT_TRUE(
        WriteExr((dir.path() / BufferName(buffer) / FileName("", buffer, 0, "exr")).string(), image)
            .ok());
  }
  absl::StatusOr<Dataset> wire = Dataset::Open(dir.path().string());
  ASSERT_TRUE(wire.ok()) << wire.status();
  absl::StatusOr<DatasetFrame> raw = wire->ReadFrame(0);
  ASSERT_TRUE(raw.ok()) << raw.status();
  EXPECT_EQ(std::get<ImageF>(raw->normals).pixels[0], -1.0f);  // as stored

  DatasetOptions linear;
  linear.exr_values = ExrValues::kLinear;
  absl::StatusOr<Dataset> converted = Dataset::Open(dir.path().string(), linear);
  ASSERT_TRUE(converted.ok());
  absl::StatusOr<DatasetFrame> frame = converted->ReadFrame(0);
  ASSERT_TRUE(frame.ok());
  EXPECT_EQ(std::get<ImageF>(frame->normals).pixels[0], 0.0f);  // -1 * 0.5 + 0.5
  // sRGB encoding of linear 0.5.
  EXPECT_NEAR(std::get<ImageF>(frame->basecolor).pixels[0], 0.735357f, 1e-5f);
  EXPECT_EQ(std::get<ImageF>(frame->depth).pixels[0], 0.5f);
}

TEST(DatasetTest, MultiLayerExrFrames) {
  ScratchDir dir;
  const ImageF basecolor = PatternF(8, 8, 3, 1), normals = PatternF(8, 8, 3, 2),
               depth = PatternF(8, 8, 1, 3), roughness = PatternF(8, 8, 1, 4),
               final_image = PatternF(8, 8, 3, 5);
  for (int f = 0; f < 2; ++f) {
    ASSERT_TRUE(
        WriteLayeredExr(dir / absl::StrFormat("Shot_%04d.exr", f), {{"BaseColor", &basecolor},
                                                                    {"WorldNormal", &normals},
                                                                    {"SceneDepth", &depth},
                                                                    {"roughness", &roughness},
                                                                    {"FinalImage", &final_image}})
            .ok());
  }
  DatasetOptions options;
  options.require_final_image = true;
  absl::StatusOr<Dataset> dataset = Dataset::Open(dir.path().string(), options);
  ASSERT_TRUE(dataset.ok()) << dataset.status();
  EXPECT_TRUE(dataset->multi_layer_exr());
  EXPECT_EQ(dataset->frames().size(), 2u);
  EXPECT_FALSE(dataset->has(Buffer::kMetallic));
  absl::StatusOr<DatasetFrame> frame = dataset->ReadFrame(1);
  ASSERT_TRUE(frame.ok()) << frame.status();
  EXPECT_EQ(std::get<ImageF>(frame->normals), normals);
  EXPECT_EQ(std::get<ImageF>(frame->depth), depth);
  EXPECT_EQ(std::get<ImageF>(frame->roughness), roughness);
  EXPECT_EQ(std::get<ImageF>(*frame->final_image), final_image);
}

TEST(DatasetTest, MultiLayerExrMissingLayer) {
  ScratchDir dir;
  const ImageF rgb = PatternF(8, 8, 3, 1), gray = PatternF(8, 8, 1, 2);
  ASSERT_TRUE(WriteLayeredExr(dir / "Frame_0000.exr",
                              {{"BaseColor", &rgb}, {"Normals", &rgb}, {"Depth", &gray}})
                  .ok());
  absl::StatusOr<Dataset> dataset = Dataset::Open(dir.path().string());
  EXPECT_EQ(dataset.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(dataset.status().message(), HasSubstr("Roughness"));
  EXPECT_THAT(dataset.status().message(), HasSubstr("Frame_0000.exr"));
}

TEST(DatasetTest, MissingBufferFileNamesTheExpectedFile) {
  ScratchDir dir;
  WriteSequence(dir.path(), "", 0, 3, kRequired);
  fs::remove(dir.path() / "Depth" / "Depth_0001.png");
  absl::StatusOr<Dataset> dataset = Dataset::Open(dir.path().string());
  EXPECT_EQ(dataset.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(dataset.status().message(), HasSubstr("missing Depth buffer for frame 1"));
  EXPECT_THAT(dataset.status().message(), HasSubstr("Depth/Depth_0001.png"));
}

TEST(DatasetTest, MissingBufferFolder) {
  ScratchDir dir;
  WriteSequence(dir.path(), "", 0, 2, {Buffer::kBaseColor, Buffer::kNormals, Buffer::kDepth});
  absl::StatusOr<Dataset> dataset = Dataset::Open(dir.path().string());
  EXPECT_EQ(dataset.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(dataset.status().message(), HasSubstr("missing buffer folder"));
  EXPECT_THAT(dataset.status().message(), HasSubstr("Roughness"));
}

TEST(DatasetTest, MismatchedFrameNumbers) {
  ScratchDir dir;
  WriteSequence(dir.path(), "", 0, 3, {Buffer::kBaseColor, Buffer::kDepth, Buffer::kRoughness});
  WriteSequence(dir.path(), "", 1, 3, {Buffer::kNormals});  // frames 1..3 instead of 0..2
  absl::StatusOr<Dataset> dataset = Dataset::Open(dir.path().string());
  EXPECT_EQ(dataset.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(dataset.status().message(), HasSubstr("mismatched frame numbers"));
  EXPECT_THAT(dataset.status().message(), HasSubstr("Normals_0003.png has no BaseColor frame 3"));
}

TEST(DatasetTest, PartialMetallicIsAnError) {
  ScratchDir dir;
  WriteSequence(dir.path(), "", 0, 3, kRequired);
  WriteSequence(dir.path(), "", 0, 2, {Buffer::kMetallic});
  absl::StatusOr<Dataset> dataset = Dataset::Open(dir.path().string());
  EXPECT_EQ(dataset.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(dataset.status().message(), HasSubstr("frame 2 has no Metallic file"));
  EXPECT_THAT(dataset.status().message(), HasSubstr("Metallic/Metallic_0002.png"));
}

TEST(DatasetTest, SizeMismatchNamesBothFiles) {
  ScratchDir dir;
  WriteSequence(dir.path(), "", 0, 2, kRequired);
  ASSERT_TRUE(WritePng(dir / "Roughness/Roughness_0001.png", Pattern8(8, 16, 1, 1)).ok());
  absl::StatusOr<Dataset> dataset = Dataset::Open(dir.path().string());
  EXPECT_EQ(dataset.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(dataset.status().message(), HasSubstr("Roughness_0001.png is 8x16"));
  EXPECT_THAT(dataset.status().message(), HasSubstr("BaseColor_0000.png is 16x16"));
}

TEST(DatasetTest, CorruptFileIsDataLoss) {
  ScratchDir dir;
  WriteSequence(dir.path(), "", 0, 2, kRequired);
  std::ofstream(dir / "Normals/Normals_0001.png", std::ios::trunc) << "garbage";
  absl::StatusOr<Dataset> dataset = Dataset::Open(dir.path().string());
  EXPECT_EQ(dataset.status().code(), absl::StatusCode::kDataLoss);
  EXPECT_THAT(dataset.status().message(), HasSubstr("Normals_0001.png"));
}

TEST(DatasetTest, RequiredFinalImage) {
  ScratchDir dir;
  WriteSequence(dir.path(), "", 0, 2, kRequired);
  DatasetOptions options;
  options.require_final_image = true;
  absl::StatusOr<Dataset> dataset = Dataset::Open(dir.path().string(), options);
  EXPECT_EQ(dataset.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(dataset.status().message(), HasSubstr("FinalImage"));
}

TEST(DatasetTest, SeveralSequencesInOneFolder) {
  ScratchDir dir;
  WriteSequence(dir.path(), "A", 0, 2, kRequired);
  WriteSequence(dir.path(), "B", 5, 3, kRequired);
  absl::StatusOr<Dataset> ambiguous = Dataset::Open(dir.path().string());
  EXPECT_EQ(ambiguous.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(ambiguous.status().message(), HasSubstr("prefixes A, B"));
  DatasetOptions options;
  options.sequence = "B";
  absl::StatusOr<Dataset> b = Dataset::Open(dir.path().string(), options);
  ASSERT_TRUE(b.ok()) << b.status();
  EXPECT_EQ(b->frames().size(), 3u);
  EXPECT_EQ(b->frames().front().index, 5);
  options.sequence = "C";
  EXPECT_EQ(Dataset::Open(dir.path().string(), options).status().code(),
            absl::StatusCode::kNotFound);
}

TEST(DatasetTest, DuplicateFrameNumbers) {
  ScratchDir dir;
  WriteSequence(dir.path(), "", 0, 2, kRequired);
  ASSERT_TRUE(WritePng(dir / "Depth/Depth_1.png", Pattern8(16, 16, 1, 1)).ok());
  absl::StatusOr<Dataset> dataset = Dataset::Open(dir.path().string());
  EXPECT_EQ(dataset.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(dataset.status().message(), HasSubstr("duplicate frame 1"));
}

TEST(DatasetTest, HierarchicalRootListsSequences) {
  ScratchDir dir;
  WriteSequence(dir.path() / "Alley", "", 0, 1, kRequired);
  WriteSequence(dir.path() / "Plaza", "", 0, 1, kRequired);
  EXPECT_EQ(ListSequenceFolders(dir.path().string()), (std::vector<std::string>{"Alley", "Plaza"}));
  absl::StatusOr<Dataset> dataset = Dataset::Open(dir.path().string());
  EXPECT_EQ(dataset.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(dataset.status().message(), HasSubstr("Alley, Plaza"));
  EXPECT_TRUE(Dataset::Open((dir.path() / "Plaza").string()).ok());
}

TEST(DatasetTest, MissingOrEmptyFolders) {
  ScratchDir dir;
  EXPECT_EQ(Dataset::Open(dir / "nope").status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(Dataset::Open(dir.path().string()).status().code(), absl::StatusCode::kNotFound);
  fs::create_directories(dir.path() / "BaseColor");
  absl::StatusOr<Dataset> empty = Dataset::Open(dir.path().string());
  EXPECT_EQ(empty.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(empty.status().message(), HasSubstr("no frames"));
}

}  // namespace
}  // namespace fd::client

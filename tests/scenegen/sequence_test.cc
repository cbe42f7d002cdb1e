// End-to-end checks of generated sequences: layout and naming as the
// reference dataset reader expects them, the sky test, normals, manifest,
// EXR output and byte-for-byte determinism.
#include "tools/scenegen/sequence.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <regex>
#include <set>

#include "tests/scenegen/scenegen_test_util.h"
#include "tools/scenegen/encoding.h"

namespace fd::scenegen {
namespace {

using testing::FreshDir;
using testing::GenerateOrDie;
using testing::ReadPngOrDie;
namespace fs = std::filesystem;

constexpr int kFrames = 3;
constexpr int kWidth = 64;
constexpr int kHeight = 48;

GeneratorOptions SmallOptions(const std::string& scene, const std::string& dir) {
  GeneratorOptions o;
  o.scene = scene;
  o.frames = kFrames;
  o.width = kWidth;
  o.height = kHeight;
  o.seed = 17;
  o.threads = 2;
  o.out_dir = dir;
  return o;
}

// Each preset is generated once per test process, when first needed.
class SequenceTest : public ::testing::TestWithParam<std::string> {
 protected:
  void SetUp() override {
    if (Dirs().count(GetParam()) == 0) {
      const std::string dir = FreshDir("sequence_" + GetParam());
      GenerateOrDie(SmallOptions(GetParam(), dir));
      Dirs()[GetParam()] = dir;
    }
  }
  static std::map<std::string, std::string>& Dirs() {
    static auto* dirs = new std::map<std::string, std::string>();
    return *dirs;
  }
  const std::string& Dir() { return Dirs()[GetParam()]; }
  Image8 Load(Buffer buffer, int frame) {
    return ReadPngOrDie(BufferPath(Dir(), buffer, frame, "png"));
  }
};

// Mirrors GBufferDataset._find_sequences/_build_dataset for a flat folder:
// FinalImage files named ^FinalImage_(\d+)\.png$, and for each frame the
// required buffers <Buffer>/<Buffer>_<same digits>.png (Metallic optional
// there, but we always write it).
TEST_P(SequenceTest, LayoutMatchesTheReferenceDatasetReader) {
  const std::regex final_pattern(R"(^FinalImage_(\d+)\.(png|jpg|jpeg)$)");
  std::set<std::string> frame_digits;
  for (const auto& entry : fs::directory_iterator(fs::path(Dir()) / "FinalImage")) {
    std::smatch match;
    const std::string name = entry.path().filename().string();
    ASSERT_TRUE(std::regex_match(name, match, final_pattern)) << name;
    frame_digits.insert(match[1].str());
  }
  EXPECT_EQ(frame_digits, (std::set<std::string>{"0000", "0001", "0002"}));
  for (const char* buffer : kBufferNames) {
    int files = 0;
    for (const auto& entry : fs::directory_iterator(fs::path(Dir()) / buffer)) {
      EXPECT_THAT(entry.path().filename().string(),
                  ::testing::MatchesRegex(std::string(buffer) + "_[0-9]{4}\\.png"));
      ++files;
    }
    EXPECT_EQ(files, kFrames) << buffer;
    for (const std::string& digits : frame_digits) {
      EXPECT_TRUE(fs::is_regular_file(fs::path(Dir()) / buffer /
                                      (std::string(buffer) + "_" + digits + ".png")))
          << buffer << " " << digits;
    }
  }
  EXPECT_TRUE(fs::is_regular_file(fs::path(Dir()) / "scene.json"));
}

TEST_P(SequenceTest, ImagesHaveTheDatasetShapes) {
  for (int k = 0; k < kNumBuffers; ++k) {
    const Image8 image = Load(static_cast<Buffer>(k), 0);
    EXPECT_EQ(image.width, kWidth) << kBufferNames[k];
    EXPECT_EQ(image.height, kHeight) << kBufferNames[k];
    EXPECT_EQ(image.channels, BufferChannels(static_cast<Buffer>(k))) << kBufferNames[k];
  }
  EXPECT_EQ(Load(Buffer::kDepth, 0).channels, 1);
  EXPECT_EQ(Load(Buffer::kNormals, 0).channels, 3);
}

// The reference's sky test must select exactly the pixels without geometry:
// those are 0 in every G-buffer, while geometry has depth >= 10.
TEST_P(SequenceTest, SkyTestSelectsExactlyTheEmptyPixels) {
  for (int frame = 0; frame < kFrames; ++frame) {
    const Image8 base = Load(Buffer::kBaseColor, frame);
    const Image8 depth = Load(Buffer::kDepth, frame);
    const Image8 normals = Load(Buffer::kNormals, frame);
    const Image8 rough = Load(Buffer::kRoughness, frame);
    const Image8 metal = Load(Buffer::kMetallic, frame);
    for (int y = 0; y < kHeight; ++y) {
      for (int x = 0; x < kWidth; ++x) {
        const bool empty = depth.at(x, y, 0) == 0;
        ASSERT_EQ(testing::SkyTest(base, depth, x, y), empty) << x << "," << y;
        if (empty) {
          for (int c = 0; c < 3; ++c) {
            ASSERT_EQ(base.at(x, y, c), 0);
            ASSERT_EQ(normals.at(x, y, c), 0);
          }
          ASSERT_EQ(rough.at(x, y, 0), 0);
          ASSERT_EQ(metal.at(x, y, 0), 0);
        } else {
          ASSERT_GE(depth.at(x, y, 0), 10) << x << "," << y;
        }
      }
    }
  }
}

TEST_P(SequenceTest, NormalsDecodeToUnitLength) {
  // Each component is off by at most half a step (1/255 in [-1, 1] units),
  // so the length is within sqrt(3)/255 of 1.
  const double tolerance = std::sqrt(3.0) / 255.0 + 1e-6;
  int checked = 0;
  for (int frame = 0; frame < kFrames; ++frame) {
    const Image8 normals = Load(Buffer::kNormals, frame);
    const Image8 depth = Load(Buffer::kDepth, frame);
    for (int y = 0; y < kHeight; ++y) {
      for (int x = 0; x < kWidth; ++x) {
        if (depth.at(x, y, 0) == 0) continue;
        double length2 = 0.0;
        for (int c = 0; c < 3; ++c) {
          const double n = normals.at(x, y, c) / 255.0 * 2.0 - 1.0;
          length2 += n * n;
        }
        ASSERT_NEAR(std::sqrt(length2), 1.0, tolerance) << x << "," << y;
        ++checked;
      }
    }
  }
  EXPECT_GT(checked, kWidth * kHeight);
}

// Both scenes look like lit scenes: neither black nor washed out, with
// texture detail, varied roughness, some metal and depth variation.
TEST_P(SequenceTest, ImagesArePlausible) {
  const Image8 final_image = Load(Buffer::kFinalImage, 0);
  const Image8 depth = Load(Buffer::kDepth, 0);
  double sum = 0.0;
  double sum2 = 0.0;
  for (int y = 0; y < kHeight; ++y) {
    for (int x = 0; x < kWidth; ++x) {
      const double l = testing::Luma(final_image, x, y);
      sum += l;
      sum2 += l * l;
    }
  }
  const double n = kWidth * kHeight;
  const double mean = sum / n;
  const double stddev = std::sqrt(std::max(0.0, sum2 / n - mean * mean));
  EXPECT_GT(mean, 30.0);
  EXPECT_LT(mean, 200.0);
  EXPECT_GT(stddev, 15.0);

  std::set<int> roughness_values;
  std::set<int> depth_values;
  int metallic_pixels = 0;
  for (int frame = 0; frame < kFrames; ++frame) {
    const Image8 rough = Load(Buffer::kRoughness, frame);
    const Image8 metal = Load(Buffer::kMetallic, frame);
    const Image8 d = Load(Buffer::kDepth, frame);
    for (size_t i = 0; i < rough.pixels.size(); ++i) {
      if (d.pixels[i] == 0) continue;
      roughness_values.insert(rough.pixels[i]);
      depth_values.insert(d.pixels[i]);
      metallic_pixels += metal.pixels[i] > 128;
    }
  }
  EXPECT_GT(roughness_values.size(), 20u);
  EXPECT_GT(depth_values.size(), 30u);
  EXPECT_GT(metallic_pixels, 0);
}

TEST_P(SequenceTest, ManifestRecordsArgumentsConventionsAndCameras) {
  std::ifstream file(fs::path(Dir()) / "scene.json");
  const nlohmann::json m = nlohmann::json::parse(file);
  EXPECT_EQ(m["arguments"]["scene"], GetParam());
  EXPECT_EQ(m["arguments"]["frames"], kFrames);
  EXPECT_EQ(m["arguments"]["width"], kWidth);
  EXPECT_EQ(m["arguments"]["height"], kHeight);
  EXPECT_EQ(m["arguments"]["seed"], 17);
  EXPECT_EQ(m["arguments"]["format"], "png");
  EXPECT_FALSE(m["arguments"].contains("threads"));  // threads never change the output
  EXPECT_THAT(m["encoding"]["Depth"].get<std::string>(), ::testing::HasSubstr("near_plane/d"));
  EXPECT_GT(m["scene"]["near_plane"].get<double>(), 0.0);
  ASSERT_EQ(m["frames"].size(), static_cast<size_t>(kFrames));
  for (int i = 0; i < kFrames; ++i) {
    EXPECT_EQ(m["frames"][i]["index"], i);
    EXPECT_EQ(m["frames"][i]["camera"]["position"].size(), 3u);
    EXPECT_EQ(m["frames"][i]["camera"]["forward"].size(), 3u);
  }
}

INSTANTIATE_TEST_SUITE_P(Scenes, SequenceTest, ::testing::Values("street", "room"));

TEST(SequenceSkyTest, StreetShowsSkyRoomShowsADarkArea) {
  const std::string dir = FreshDir("sky_and_dark");
  GenerateOrDie(SmallOptions("street", dir + "/street"));
  GenerateOrDie(SmallOptions("room", dir + "/room"));
  // Street: open sky, bluish, in the top part of the frame.
  const Image8 base = ReadPngOrDie(BufferPath(dir + "/street", Buffer::kBaseColor, 0, "png"));
  const Image8 depth = ReadPngOrDie(BufferPath(dir + "/street", Buffer::kDepth, 0, "png"));
  const Image8 final_image =
      ReadPngOrDie(BufferPath(dir + "/street", Buffer::kFinalImage, 0, "png"));
  int sky = 0;
  int bluish = 0;
  for (int y = 0; y < kHeight; ++y) {
    for (int x = 0; x < kWidth; ++x) {
      if (!testing::SkyTest(base, depth, x, y)) continue;
      ++sky;
      bluish += final_image.at(x, y, 2) > final_image.at(x, y, 0);
    }
  }
  EXPECT_GT(sky, kWidth * kHeight / 20);
  EXPECT_GT(bluish, sky * 9 / 10);

  // Room: a dark area (the unlit back room) beside sunlit parts, all of it
  // geometry with a non-black base colour.
  const Image8 room = ReadPngOrDie(BufferPath(dir + "/room", Buffer::kFinalImage, 0, "png"));
  const Image8 room_depth = ReadPngOrDie(BufferPath(dir + "/room", Buffer::kDepth, 0, "png"));
  int dark = 0;
  int bright = 0;
  int geometry = 0;
  for (int y = 0; y < kHeight; ++y) {
    for (int x = 0; x < kWidth; ++x) {
      if (room_depth.at(x, y, 0) == 0) continue;
      ++geometry;
      const float l = testing::Luma(room, x, y);
      dark += l < 20.0f;
      bright += l > 150.0f;
    }
  }
  EXPECT_GT(geometry, kWidth * kHeight * 9 / 10);
  EXPECT_GT(dark, geometry / 50) << "no dark area";
  EXPECT_GT(bright, geometry / 50) << "no sunlit area";
}

TEST(SequenceDeterminismTest, SameArgumentsGiveIdenticalFilesForAnyThreadCount) {
  const std::string dir = FreshDir("determinism");
  GeneratorOptions a = SmallOptions("street", dir + "/a");
  a.format = OutputFormat::kBoth;
  GeneratorOptions b = a;
  b.out_dir = dir + "/b";
  b.threads = 1;
  GeneratorOptions c = a;
  c.out_dir = dir + "/c";
  GenerateOrDie(a);
  GenerateOrDie(b);
  GenerateOrDie(c);
  const auto hashes_a = testing::HashTree(a.out_dir);
  EXPECT_EQ(hashes_a.size(), 2u * kNumBuffers * kFrames + 1);  // + scene.json
  EXPECT_EQ(hashes_a, testing::HashTree(b.out_dir));           // 2 threads vs 1
  EXPECT_EQ(hashes_a, testing::HashTree(c.out_dir));           // a second run

  GeneratorOptions other_seed = a;
  other_seed.out_dir = dir + "/d";
  other_seed.seed = 18;
  GenerateOrDie(other_seed);
  EXPECT_NE(hashes_a, testing::HashTree(other_seed.out_dir));
}

// Frame k is the same image whether rendered in a long run or a shard.
TEST(SequenceDeterminismTest, StartFrameRendersTheSameFrames) {
  const std::string dir = FreshDir("start_frame");
  GeneratorOptions all = SmallOptions("room", dir + "/all");
  GeneratorOptions shard = all;
  shard.out_dir = dir + "/shard";
  shard.start_frame = 2;
  shard.frames = 1;
  GenerateOrDie(all);
  GenerateOrDie(shard);
  EXPECT_FALSE(fs::exists(BufferPath(shard.out_dir, Buffer::kFinalImage, 0, "png")));
  for (int k = 0; k < kNumBuffers; ++k) {
    EXPECT_EQ(testing::ReadBytes(BufferPath(all.out_dir, static_cast<Buffer>(k), 2, "png")),
              testing::ReadBytes(BufferPath(shard.out_dir, static_cast<Buffer>(k), 2, "png")))
        << kBufferNames[k];
  }
}

// EXR files sit beside the PNGs and hold the same data at float precision.
TEST(SequenceExrTest, ExrOutputIsReadableAndMatchesThePngs) {
  const std::string dir = FreshDir("exr");
  GeneratorOptions o = SmallOptions("street", dir);
  o.frames = 1;
  o.format = OutputFormat::kBoth;
  GenerateOrDie(o);
  std::ifstream file(fs::path(dir) / "scene.json");
  const float near_plane = nlohmann::json::parse(file)["scene"]["near_plane"].get<float>();

  std::array<ImageF, kNumBuffers> exr;
  for (int k = 0; k < kNumBuffers; ++k) {
    absl::StatusOr<ImageF> image = ReadExr(BufferPath(dir, static_cast<Buffer>(k), 0, "exr"));
    ASSERT_TRUE(image.ok()) << image.status();
    EXPECT_EQ(image->width, kWidth);
    EXPECT_EQ(image->height, kHeight);
    EXPECT_EQ(image->channels, BufferChannels(static_cast<Buffer>(k)));
    exr[k] = *image;
  }
  const Image8 final_png = ReadPngOrDie(BufferPath(dir, Buffer::kFinalImage, 0, "png"));
  const Image8 base_png = ReadPngOrDie(BufferPath(dir, Buffer::kBaseColor, 0, "png"));
  const Image8 depth_png = ReadPngOrDie(BufferPath(dir, Buffer::kDepth, 0, "png"));
  const Image8 normals_png = ReadPngOrDie(BufferPath(dir, Buffer::kNormals, 0, "png"));
  const Image8 rough_png = ReadPngOrDie(BufferPath(dir, Buffer::kRoughness, 0, "png"));
  const ImageF& final_exr = exr[static_cast<int>(Buffer::kFinalImage)];
  const ImageF& base_exr = exr[static_cast<int>(Buffer::kBaseColor)];
  const ImageF& depth_exr = exr[static_cast<int>(Buffer::kDepth)];
  const ImageF& normals_exr = exr[static_cast<int>(Buffer::kNormals)];
  const ImageF& rough_exr = exr[static_cast<int>(Buffer::kRoughness)];
  for (int y = 0; y < kHeight; ++y) {
    for (int x = 0; x < kWidth; ++x) {
      ASSERT_EQ(depth_exr.at(x, y, 0) == 0.0f, depth_png.at(x, y, 0) == 0);
      if (depth_exr.at(x, y, 0) > 0.0f) {
        // PNG depth is the EXR value quantised and far-clamped.
        const float metres = near_plane / depth_exr.at(x, y, 0);
        ASSERT_EQ(depth_png.at(x, y, 0), EncodeDepth(metres, near_plane));
      }
      for (int c = 0; c < 3; ++c) {
        ASSERT_EQ(final_png.at(x, y, c), ToByte(LinearToSrgb(ToneMapAces(final_exr.at(x, y, c)))));
        ASSERT_EQ(base_png.at(x, y, c), ToByte(LinearToSrgb(base_exr.at(x, y, c))));
        if (depth_png.at(x, y, 0) > 0) {
          ASSERT_EQ(normals_png.at(x, y, c), EncodeNormalComponent(normals_exr.at(x, y, c)));
        }
      }
      ASSERT_EQ(rough_png.at(x, y, 0), ToByte(rough_exr.at(x, y, 0)));
    }
  }
}

TEST(SequenceExrTest, ExrOnlyWritesNoPngs) {
  const std::string dir = FreshDir("exr_only");
  GeneratorOptions o = SmallOptions("room", dir);
  o.frames = 1;
  o.format = OutputFormat::kExr;
  GenerateOrDie(o);
  for (int k = 0; k < kNumBuffers; ++k) {
    EXPECT_TRUE(fs::exists(BufferPath(dir, static_cast<Buffer>(k), 0, "exr")));
    EXPECT_FALSE(fs::exists(BufferPath(dir, static_cast<Buffer>(k), 0, "png")));
  }
}

TEST(SequenceOptionsTest, BadOptionsAreRejected) {
  const std::string dir = FreshDir("bad_options");
  GeneratorOptions o = SmallOptions("street", dir);
  o.scene = "moon";
  EXPECT_EQ(GenerateSequence(o).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(GenerateSequence(o).status().message()), ::testing::HasSubstr("moon"));
  o = SmallOptions("street", dir);
  o.frames = 0;
  EXPECT_EQ(GenerateSequence(o).status().code(), absl::StatusCode::kInvalidArgument);
  o = SmallOptions("street", dir);
  o.width = 0;
  EXPECT_EQ(GenerateSequence(o).status().code(), absl::StatusCode::kInvalidArgument);
  o = SmallOptions("street", "");
  EXPECT_EQ(GenerateSequence(o).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(BufferFileName(Buffer::kRoughness, 12345, "png"), "Roughness_12345.png");
  EXPECT_EQ(BufferFileName(Buffer::kFinalImage, 7, "exr"), "FinalImage_0007.exr");
}

}  // namespace
}  // namespace fd::scenegen

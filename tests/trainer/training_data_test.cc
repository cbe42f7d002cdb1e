// trainer/training_data.h: the layouts it reads and every bad-data case,
// each with an error that names the file or folder.
#include "trainer/training_data.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <filesystem>
#include <fstream>

#include "absl/strings/match.h"
#include "client_sdk/image_io.h"
#include "tests/trainer/trainer_test_util.h"

namespace fd::trainer {
namespace {

namespace fs = std::filesystem;

class TrainingDataTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = testing::MakeTempDir("data");
    seq_ = dir_ + "/street_a";
    testing::WriteSequence(seq_, {5, 40, 24, 1, true, true});
  }
  void TearDown() override { fs::remove_all(dir_); }

  absl::StatusOr<TrainingData> Load(const std::vector<std::string>& dirs) {
    TrainingDataOptions options;
    options.width = 16;
    options.height = 16;
    return LoadTrainingData(dirs, options);
  }

  std::string dir_, seq_;
};

TEST_F(TrainingDataTest, ReadsAndResizesEveryBuffer) {
  absl::StatusOr<TrainingData> data = Load({seq_});
  ASSERT_TRUE(data.ok()) << data.status();
  ASSERT_EQ(data->sequences.size(), 1u);
  const TrainingSequence& s = data->sequences[0];
  EXPECT_EQ(s.size(), 5);
  EXPECT_EQ(s.frame_numbers, (std::vector<int64_t>{0, 1, 2, 3, 4}));
  EXPECT_EQ(s.final_image.sizes(), torch::IntArrayRef({5, 3, 16, 16}));
  EXPECT_EQ(s.depth.sizes(), torch::IntArrayRef({5, 1, 16, 16}));
  EXPECT_EQ(s.metallic.scalar_type(), torch::kUInt8);
  EXPECT_GT(s.metallic.max().item<int>(), 0);
  EXPECT_EQ(data->frame_count(), 5);
}

TEST_F(TrainingDataTest, KeepsTheNativeSizeExactly) {
  TrainingDataOptions options;
  options.width = 40;
  options.height = 24;
  absl::StatusOr<TrainingData> data = LoadTrainingData({seq_}, options);
  ASSERT_TRUE(data.ok()) << data.status();
  absl::StatusOr<fd::client::Image8> png =
      fd::client::ReadPng(seq_ + "/FinalImage/FinalImage_0002.png");
  ASSERT_TRUE(png.ok());
  EXPECT_EQ(data->sequences[0].final_image[2][1][5][7].item<int>(), png->at(7, 5, 1));
}

TEST_F(TrainingDataTest, ReadsTheExrVariantsLikeThePngs) {
  // The same sequence as float EXRs in the wire encoding ([0, 1]).
  const std::string exr = dir_ + "/exr";
  for (const char* buffer :
       {"FinalImage", "BaseColor", "Normals", "Depth", "Roughness", "Metallic"}) {
    fs::create_directories(exr + "/" + buffer);
    for (int f = 0; f < 5; ++f) {
      const std::string name = std::string(buffer) + "_000" + std::to_string(f);
      absl::StatusOr<fd::client::Image8> png =
          fd::client::ReadPng(seq_ + "/" + buffer + "/" + name + ".png");
      ASSERT_TRUE(png.ok()) << png.status();
      ASSERT_TRUE(fd::client::WriteExr(exr + "/" + buffer + "/" + name + ".exr",
                                       fd::client::ToFloat(fd::client::ImageView::Of(*png)))
                      .ok());
    }
  }
  absl::StatusOr<TrainingData> from_png = Load({seq_});
  absl::StatusOr<TrainingData> from_exr = Load({exr});
  ASSERT_TRUE(from_png.ok()) << from_png.status();
  ASSERT_TRUE(from_exr.ok()) << from_exr.status();
  const TrainingSequence &a = from_png->sequences[0], &b = from_exr->sequences[0];
  EXPECT_TRUE(torch::equal(a.final_image, b.final_image));
  EXPECT_TRUE(torch::equal(a.normals, b.normals));
  EXPECT_TRUE(torch::equal(a.depth, b.depth));
  EXPECT_TRUE(torch::equal(a.metallic, b.metallic));
}

TEST_F(TrainingDataTest, MissingMetallicIsZeros) {
  fs::remove_all(seq_ + "/Metallic");
  absl::StatusOr<TrainingData> data = Load({seq_});
  ASSERT_TRUE(data.ok()) << data.status();
  EXPECT_EQ(data->sequences[0].metallic.max().item<int>(), 0);
}

TEST_F(TrainingDataTest, AFolderOfSequencesGivesEachSequence) {
  testing::WriteSequence(dir_ + "/street_b", {4, 40, 24, 2, true, true});
  absl::StatusOr<TrainingData> data = Load({dir_});
  ASSERT_TRUE(data.ok()) << data.status();
  EXPECT_EQ(data->sequences.size(), 2u);
  EXPECT_EQ(data->frame_count(), 9);
}

struct BadCase {
  const char* name;
  void (*damage)(const std::string& seq);
  absl::StatusCode code;
  const char* message_part;
};

class BadDataTest : public TrainingDataTest, public ::testing::WithParamInterface<BadCase> {};

TEST_P(BadDataTest, IsRejectedNamingTheFile) {
  GetParam().damage(seq_);
  absl::StatusOr<TrainingData> data = Load({seq_});
  ASSERT_FALSE(data.ok());
  EXPECT_EQ(data.status().code(), GetParam().code) << data.status();
  EXPECT_TRUE(absl::StrContains(data.status().message(), GetParam().message_part)) << data.status();
}

INSTANTIATE_TEST_SUITE_P(
    Cases, BadDataTest,
    ::testing::Values(BadCase{"missing_buffer_folder",
                              [](const std::string& s) { fs::remove_all(s + "/Normals"); },
                              absl::StatusCode::kNotFound, "Normals"},
                      BadCase{"missing_final_image",
                              [](const std::string& s) { fs::remove_all(s + "/FinalImage"); },
                              absl::StatusCode::kNotFound, "FinalImage"},
                      BadCase{"frame_counts_differ",
                              [](const std::string& s) { fs::remove(s + "/Depth/Depth_0003.png"); },
                              absl::StatusCode::kNotFound, "Depth_0003"},
                      BadCase{"mismatched_sizes",
                              [](const std::string& s) {
                                ASSERT_TRUE(
                                    fd::client::WritePng(s + "/Roughness/Roughness_0001.png",
                                                         fd::client::Image8(8, 8, 1))
                                        .ok());
                              },
                              absl::StatusCode::kInvalidArgument, "Roughness_0001.png"},
                      BadCase{"unreadable_png",
                              [](const std::string& s) {
                                std::ofstream(s + "/BaseColor/BaseColor_0002.png") << "not a png";
                              },
                              absl::StatusCode::kDataLoss, "BaseColor_0002.png"},
                      BadCase{"shorter_than_the_offset_range",
                              [](const std::string& s) {
                                for (const char* b : {"FinalImage", "BaseColor", "Normals", "Depth",
                                                      "Roughness", "Metallic"}) {
                                  for (int f = 2; f < 5; ++f) {
                                    fs::remove(s + "/" + b + "/" + b + "_000" + std::to_string(f) +
                                               ".png");
                                  }
                                }
                              },
                              absl::StatusCode::kInvalidArgument, "at least 3"}),
    [](const ::testing::TestParamInfo<BadCase>& info) { return std::string(info.param.name); });

TEST_F(TrainingDataTest, EmptyAndMissingDatasetsAreRejected) {
  EXPECT_EQ(Load({}).status().code(), absl::StatusCode::kInvalidArgument);
  fs::create_directories(dir_ + "/empty");
  absl::StatusOr<TrainingData> empty = Load({dir_ + "/empty"});
  ASSERT_FALSE(empty.ok());
  EXPECT_TRUE(absl::StrContains(empty.status().message(), "empty")) << empty.status();
  absl::StatusOr<TrainingData> missing = Load({dir_ + "/nope"});
  EXPECT_EQ(missing.status().code(), absl::StatusCode::kNotFound);
  EXPECT_TRUE(absl::StrContains(missing.status().message(), "nope"));
  TrainingDataOptions odd;
  odd.width = 30;
  EXPECT_EQ(LoadTrainingData({seq_}, odd).status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace fd::trainer

// Tests for model/safetensors.{h,cc}: round trips of every supported dtype,
// real golden files, and one test per kind of corrupt file (each checks the
// status code and that the message names the file and the tensor).
#include "model/checkpoint/safetensors.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <sys/stat.h>
#include <torch/torch.h>
#include <unistd.h>

#include <cstdint>
#include <cstring>
#include <fstream>
#include <string>
#include <vector>

#include "tests/testing/golden.h"

namespace fd::model {
namespace {

using ::testing::HasSubstr;

// A per-process directory under the gtest temp dir, so that concurrent runs
// of this binary (ctest -j, several build trees) never share files.
std::string TempPath(const std::string& name) {
  static const std::string dir = [] {
    std::string path = ::testing::TempDir() + "/fd_safetensors_test_" + std::to_string(::getpid());
    ::mkdir(path.c_str(), 0700);
    return path;
  }();
  return dir + "/" + name;
}

// Writes a safetensors-like file byte by byte: an 8-byte little-endian length
// (`header.size()` unless `declared_header_size` is given), the header text
// and `data_size` bytes of data.
void WriteRawFile(const std::string& path, const std::string& header, size_t data_size,
                  int64_t declared_header_size = -1) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  const uint64_t size = declared_header_size >= 0 ? static_cast<uint64_t>(declared_header_size)
                                                  : static_cast<uint64_t>(header.size());
  out.write(reinterpret_cast<const char*>(&size), sizeof(size));
  out.write(header.data(), static_cast<std::streamsize>(header.size()));
  const std::string data(data_size, '\x01');
  out.write(data.data(), static_cast<std::streamsize>(data.size()));
  ASSERT_TRUE(out.good()) << path;
}

std::string ReadBytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
}

// Opens `path`, expects INVALID_ARGUMENT whose message names the file and
// every string in `also_named`.
void ExpectCorrupt(const std::string& path, const std::vector<std::string>& also_named) {
  auto file = SafetensorsFile::Open(path);
  ASSERT_FALSE(file.ok()) << "opened a corrupt file: " << path;
  EXPECT_EQ(file.status().code(), absl::StatusCode::kInvalidArgument) << file.status();
  EXPECT_THAT(std::string(file.status().message()), HasSubstr(path));
  for (const std::string& name : also_named) {
    EXPECT_THAT(std::string(file.status().message()), HasSubstr(name));
  }
}

TEST(SafetensorsTest, RoundTripsEverySupportedDtypeIncludingScalarsAndEmptyTensors) {
  torch::manual_seed(7);
  std::map<std::string, torch::Tensor> tensors = {
      {"f64", torch::randn({3, 2}, torch::kFloat64)},
      {"f32", torch::randn({2, 3, 4})},
      {"f16", torch::randn({5}).to(torch::kFloat16)},
      {"bf16", torch::randn({2, 2}).to(torch::kBFloat16)},
      {"i64", torch::randint(-1000000, 1000000, {4}, torch::kInt64)},
      {"i32", torch::randint(-100000, 100000, {2, 2}, torch::kInt32)},
      {"i16", torch::randint(-30000, 30000, {3}, torch::kInt16)},
      {"i8", torch::randint(-128, 127, {6}, torch::kInt8)},
      {"u8", torch::randint(0, 255, {2, 3, 3}, torch::kUInt8)},
      {"bool", torch::randint(0, 2, {7}, torch::kInt64).to(torch::kBool)},
      {"scalar_f32", torch::tensor(3.5f)},
      {"scalar_i64", torch::tensor(int64_t{481})},
      {"empty_f32", torch::empty({0, 3})},
      {"empty_u8", torch::empty({4, 0}, torch::kUInt8)},
      // Non-contiguous input: stored contiguous.
      {"transposed", torch::randn({3, 4}).t()},
  };
  const std::map<std::string, std::string> metadata = {{"format", "pt"}, {"set", "unit"}};
  const std::string path = TempPath("round_trip.safetensors");
  ASSERT_TRUE(SaveSafetensors(path, tensors, metadata).ok());

  auto file = SafetensorsFile::Open(path);
  ASSERT_TRUE(file.ok()) << file.status();
  EXPECT_EQ((*file)->path(), path);
  EXPECT_EQ((*file)->metadata(), metadata);
  std::vector<std::string> expected_keys;
  for (const auto& [name, tensor] : tensors) expected_keys.push_back(name);
  EXPECT_EQ((*file)->Keys(), expected_keys);
  EXPECT_EQ((*file)->Info("f16")->dtype, "F16");
  EXPECT_EQ((*file)->Info("bf16")->dtype, "BF16");
  EXPECT_EQ((*file)->Info("bool")->dtype, "BOOL");
  EXPECT_TRUE((*file)->Info("scalar_f32")->shape.empty());

  for (const auto& [name, expected] : tensors) {
    SCOPED_TRACE(name);
    EXPECT_TRUE((*file)->Contains(name));
    auto actual = (*file)->Get(name);
    ASSERT_TRUE(actual.ok()) << actual.status();
    EXPECT_EQ(actual->scalar_type(), expected.scalar_type());
    EXPECT_EQ(actual->sizes(), expected.sizes());
    EXPECT_TRUE(actual->is_contiguous());
    EXPECT_TRUE(torch::equal(*actual, expected));
  }

  // The tensors are owning copies: they outlive the file.
  torch::Tensor f32 = *(*file)->Get("f32");
  file->reset();
  EXPECT_TRUE(torch::equal(f32, tensors.at("f32")));

  auto loaded = LoadSafetensors(path);
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  ASSERT_EQ(loaded->size(), tensors.size());
  for (const auto& [name, expected] : tensors) {
    EXPECT_TRUE(torch::equal(loaded->at(name), expected)) << name;
  }
}

TEST(SafetensorsTest, HeaderIsPaddedSoTheDataSectionIsEightByteAligned) {
  const std::string path = TempPath("aligned.safetensors");
  ASSERT_TRUE(SaveSafetensors(path, {{"x", torch::ones({3})}, {"abc", torch::zeros({1})}}).ok());
  const std::string bytes = ReadBytes(path);
  ASSERT_GE(bytes.size(), 8u);
  uint64_t header_size = 0;
  std::memcpy(&header_size, bytes.data(), 8);
  EXPECT_EQ(header_size % 8, 0u);
  // Data in key order: "abc" (4 bytes) first, then "x" (12 bytes).
  EXPECT_EQ(bytes.size(), 8 + header_size + 16);
  const std::string header = bytes.substr(8, header_size);
  EXPECT_LT(header.find("\"abc\""), header.find("\"x\""));
  EXPECT_THAT(header, HasSubstr("\"data_offsets\":[4,16]"));
  // Padding is spaces after the JSON.
  EXPECT_EQ(header.find_last_not_of(' '), header.rfind('}'));
}

TEST(SafetensorsTest, SaveWithNoTensorsWritesAValidFile) {
  const std::string path = TempPath("empty_file.safetensors");
  ASSERT_TRUE(SaveSafetensors(path, {}).ok());
  auto file = SafetensorsFile::Open(path);
  ASSERT_TRUE(file.ok()) << file.status();
  EXPECT_TRUE((*file)->Keys().empty());
  EXPECT_TRUE((*file)->metadata().empty());
}

TEST(SafetensorsTest, SaveRejectsUnsupportedDtypeNamingTheTensor) {
  const std::string path = TempPath("complex.safetensors");
  const absl::Status status = SaveSafetensors(
      path, {{"ok", torch::ones({2})}, {"spectrum", torch::ones({2}, torch::kComplexFloat)}});
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument) << status;
  EXPECT_THAT(std::string(status.message()), HasSubstr("spectrum"));
  EXPECT_THAT(std::string(status.message()), HasSubstr(path));
  // Nothing was written, not even a temporary file left behind at `path`.
  EXPECT_FALSE(std::ifstream(path).good());
}

TEST(SafetensorsTest, SaveIntoMissingDirectoryIsInternalError) {
  const std::string path = TempPath("no_such_dir/x.safetensors");
  const absl::Status status = SaveSafetensors(path, {{"x", torch::ones({2})}});
  EXPECT_EQ(status.code(), absl::StatusCode::kInternal) << status;
  EXPECT_THAT(std::string(status.message()), HasSubstr("no_such_dir"));
}

TEST(SafetensorsTest, MissingFileIsNotFoundNamingThePath) {
  const std::string path = TempPath("does_not_exist.safetensors");
  auto file = SafetensorsFile::Open(path);
  ASSERT_FALSE(file.ok());
  EXPECT_EQ(file.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(std::string(file.status().message()), HasSubstr(path));
  EXPECT_EQ(LoadSafetensors(path).status().code(), absl::StatusCode::kNotFound);
}

TEST(SafetensorsTest, MissingKeyIsNotFoundNamingFileAndKey) {
  const std::string path = TempPath("one_key.safetensors");
  ASSERT_TRUE(SaveSafetensors(path, {{"present", torch::ones({1})}}).ok());
  auto file = SafetensorsFile::Open(path);
  ASSERT_TRUE(file.ok()) << file.status();
  EXPECT_FALSE((*file)->Contains("absent"));
  for (const absl::Status& status :
       {(*file)->Get("absent").status(), (*file)->Info("absent").status()}) {
    EXPECT_EQ(status.code(), absl::StatusCode::kNotFound);
    EXPECT_THAT(std::string(status.message()), HasSubstr("absent"));
    EXPECT_THAT(std::string(status.message()), HasSubstr(path));
  }
}

// A real golden file written by the reference generator: every tensor the
// header lists can be read with its declared shape and dtype, the values are
// finite, and a save/open round trip preserves them exactly.
TEST(SafetensorsTest, ReadsGoldenFloatFile) {
  const std::string path = fd::testing::GoldenPath("A/golden/inputs.safetensors");
  auto file = SafetensorsFile::Open(path);
  ASSERT_TRUE(file.ok()) << file.status();
  const std::vector<std::string> keys = (*file)->Keys();
  ASSERT_FALSE(keys.empty());
  EXPECT_FALSE((*file)->metadata().empty());  // goldens carry provenance metadata
  std::map<std::string, torch::Tensor> all;
  int float_tensors = 0;
  for (const std::string& key : keys) {
    SCOPED_TRACE(key);
    auto info = (*file)->Info(key);
    ASSERT_TRUE(info.ok()) << info.status();
    auto tensor = (*file)->Get(key);
    ASSERT_TRUE(tensor.ok()) << tensor.status();
    EXPECT_EQ(tensor->sizes().vec(), info->shape);
    if (info->dtype == "F32") {
      ++float_tensors;
      EXPECT_EQ(tensor->scalar_type(), torch::kFloat32);
      EXPECT_TRUE(torch::isfinite(*tensor).all().item<bool>());
    }
    all.emplace(key, *tensor);
  }
  EXPECT_GT(float_tensors, 0);
  if ((*file)->Contains("timestep")) {
    EXPECT_EQ((*file)->Get("timestep")->scalar_type(), torch::kInt64);
  }
  // U[0,1) inputs (golden README) really decode to values in [0, 1).
  if ((*file)->Contains("prev_image")) {
    const torch::Tensor image = *(*file)->Get("prev_image");
    EXPECT_GE(image.min().item<float>(), 0.0f);
    EXPECT_LT(image.max().item<float>(), 1.0f);
  }

  const std::string copy_path = TempPath("golden_copy.safetensors");
  ASSERT_TRUE(SaveSafetensors(copy_path, all, (*file)->metadata()).ok());
  auto copy = LoadSafetensors(copy_path);
  ASSERT_TRUE(copy.ok()) << copy.status();
  for (const auto& [key, tensor] : all) {
    EXPECT_TRUE(torch::equal(copy->at(key), tensor)) << key;
  }
}

TEST(SafetensorsTest, ReadsGoldenUint8File) {
  const std::string path = fd::testing::GoldenPath("fd_pipeline/golden/e2e_inputs.safetensors");
  auto file = SafetensorsFile::Open(path);
  ASSERT_TRUE(file.ok()) << file.status();
  int uint8_tensors = 0;
  for (const std::string& key : (*file)->Keys()) {
    SCOPED_TRACE(key);
    auto tensor = (*file)->Get(key);
    ASSERT_TRUE(tensor.ok()) << tensor.status();
    EXPECT_EQ(tensor->sizes().vec(), (*file)->Info(key)->shape);
    if ((*file)->Info(key)->dtype != "U8") continue;
    ++uint8_tensors;
    EXPECT_EQ(tensor->scalar_type(), torch::kUInt8);
    // Images are HWC: the last dim is the channel count (3) or the image is
    // single channel [H, W].
    ASSERT_GE(tensor->dim(), 2);
    if (tensor->dim() == 3) {
      EXPECT_EQ(tensor->size(2), 3);
    }
  }
  EXPECT_GT(uint8_tensors, 0);
}

// ---------------------------------------------------------------------------
// One test per corruption kind.

TEST(SafetensorsCorruptionTest, TruncatedFileShorterThanLengthField) {
  const std::string path = TempPath("short.safetensors");
  std::ofstream(path, std::ios::binary) << "abcde";
  ExpectCorrupt(path, {"5 bytes"});
  // An empty file too.
  const std::string empty_path = TempPath("zero.safetensors");
  std::ofstream(empty_path, std::ios::binary).close();
  ExpectCorrupt(empty_path, {"0 bytes"});
}

TEST(SafetensorsCorruptionTest, TruncatedDataSection) {
  // A valid file cut short: the last tensor's bytes are missing.
  const std::string path = TempPath("truncated_data.safetensors");
  ASSERT_TRUE(SaveSafetensors(path, {{"a", torch::ones({4})}, {"b", torch::ones({8})}}).ok());
  std::string bytes = ReadBytes(path);
  bytes.resize(bytes.size() - 5);
  std::ofstream(path, std::ios::binary | std::ios::trunc) << bytes;
  ExpectCorrupt(path, {"'b'", "out of range"});
}

// A file that another process truncates after Open() validated it (a `cp`
// over a checkpoint while a reload reads it): Get() of a tensor past the new
// end is DATA_LOSS naming the file and the tensor, not SIGBUS (which reading
// through a memory mapping would raise); tensors still inside the file read.
TEST(SafetensorsCorruptionTest, FileTruncatedAfterOpenIsDataLossNotSigbus) {
  const std::string path = TempPath("truncated_after_open.safetensors");
  const torch::Tensor first = torch::arange(1024, torch::kFloat32);
  ASSERT_TRUE(SaveSafetensors(path, {{"a_first", first}, {"z_last", torch::ones({4096})}}).ok());
  auto file = SafetensorsFile::Open(path);
  ASSERT_TRUE(file.ok()) << file.status();
  auto last_info = (*file)->Info("z_last");
  ASSERT_TRUE(last_info.ok()) << last_info.status();
  const std::string bytes = ReadBytes(path);
  const size_t data_begin = bytes.size() - last_info->end;
  // Cut the file in the middle of z_last's bytes, after a_first's.
  ASSERT_EQ(::truncate(path.c_str(), static_cast<off_t>(data_begin + last_info->begin + 100)), 0);

  auto last = (*file)->Get("z_last");
  ASSERT_FALSE(last.ok());
  EXPECT_EQ(last.status().code(), absl::StatusCode::kDataLoss) << last.status();
  EXPECT_THAT(std::string(last.status().message()), HasSubstr(path));
  EXPECT_THAT(std::string(last.status().message()), HasSubstr("'z_last'"));
  auto kept = (*file)->Get("a_first");
  ASSERT_TRUE(kept.ok()) << kept.status();
  EXPECT_TRUE(torch::equal(*kept, first));
}

TEST(SafetensorsCorruptionTest, HeaderLengthPastEndOfFile) {
  const std::string path = TempPath("header_past_eof.safetensors");
  WriteRawFile(path, R"({"x":{"dtype":"F32","shape":[1],"data_offsets":[0,4]}})", 4,
               /*declared_header_size=*/1 << 20);
  ExpectCorrupt(path, {"header length 1048576"});
}

TEST(SafetensorsCorruptionTest, OverlappingOffsets) {
  const std::string path = TempPath("overlap.safetensors");
  WriteRawFile(path,
               R"({"first":{"dtype":"F32","shape":[4],"data_offsets":[0,16]},)"
               R"("second":{"dtype":"F32","shape":[4],"data_offsets":[8,24]}})",
               24);
  ExpectCorrupt(path, {"'second'", "'first'", "overlap"});
}

TEST(SafetensorsCorruptionTest, OutOfRangeOffsets) {
  const std::string path = TempPath("out_of_range.safetensors");
  WriteRawFile(path, R"({"weight":{"dtype":"F32","shape":[4],"data_offsets":[16,32]}})", 20);
  ExpectCorrupt(path, {"'weight'", "out of range"});
}

TEST(SafetensorsCorruptionTest, BeginAfterEnd) {
  const std::string path = TempPath("begin_after_end.safetensors");
  WriteRawFile(path, R"({"weight":{"dtype":"F32","shape":[0],"data_offsets":[8,4]}})", 16);
  ExpectCorrupt(path, {"'weight'", "greater than end"});
}

TEST(SafetensorsCorruptionTest, UnknownDtype) {
  const std::string path = TempPath("unknown_dtype.safetensors");
  WriteRawFile(path, R"({"weight":{"dtype":"F8_E4M3","shape":[4],"data_offsets":[0,4]}})", 4);
  ExpectCorrupt(path, {"'weight'", "F8_E4M3"});
}

TEST(SafetensorsCorruptionTest, BadJson) {
  const std::string path = TempPath("bad_json.safetensors");
  WriteRawFile(path, R"({"weight":{"dtype":"F32","shape":[1],"data_offsets":[0,4]})", 4);
  ExpectCorrupt(path, {"not valid JSON"});
}

TEST(SafetensorsCorruptionTest, HeaderNotAnObject) {
  const std::string path = TempPath("array_header.safetensors");
  WriteRawFile(path, R"([1, 2, 3])", 0);
  ExpectCorrupt(path, {"expected an object"});
}

TEST(SafetensorsCorruptionTest, SizeMismatch) {
  const std::string path = TempPath("size_mismatch.safetensors");
  // [2, 3] float32 needs 24 bytes; the offsets give 20.
  WriteRawFile(path, R"({"weight":{"dtype":"F32","shape":[2,3],"data_offsets":[0,20]}})", 24);
  ExpectCorrupt(path, {"'weight'", "20 bytes", "needs 24 bytes"});
}

TEST(SafetensorsCorruptionTest, NegativeDimension) {
  const std::string path = TempPath("negative_dim.safetensors");
  WriteRawFile(path, R"({"weight":{"dtype":"F32","shape":[-1,4],"data_offsets":[0,16]}})", 16);
  ExpectCorrupt(path, {"'weight'", "negative dimension -1"});
}

TEST(SafetensorsCorruptionTest, MissingOrMistypedFields) {
  struct Case {
    const char* header;
    const char* expected;
  };
  const Case cases[] = {
      {R"({"w":{"shape":[1],"data_offsets":[0,4]}})", "missing 'dtype'"},
      {R"({"w":{"dtype":"F32","data_offsets":[0,4]}})", "missing 'shape'"},
      {R"({"w":{"dtype":"F32","shape":[1]}})", "missing 'data_offsets'"},
      {R"({"w":{"dtype":32,"shape":[1],"data_offsets":[0,4]}})", "'dtype' is not a string"},
      {R"({"w":{"dtype":"F32","shape":"1","data_offsets":[0,4]}})", "'shape' is not an array"},
      {R"({"w":{"dtype":"F32","shape":[1.5],"data_offsets":[0,4]}})", "non-integer dimension"},
      {R"({"w":{"dtype":"F32","shape":[1],"data_offsets":[0]}})", "two non-negative integers"},
      {R"({"w":{"dtype":"F32","shape":[1],"data_offsets":[-4,4]}})", "two non-negative integers"},
      {R"({"w":[1,2]})", "not a JSON object"},
  };
  int index = 0;
  for (const Case& c : cases) {
    SCOPED_TRACE(c.header);
    const std::string path = TempPath("fields_" + std::to_string(index++) + ".safetensors");
    WriteRawFile(path, c.header, 4);
    ExpectCorrupt(path, {"'w'", c.expected});
  }
}

TEST(SafetensorsCorruptionTest, MetadataNotStringToStringMap) {
  const std::string path = TempPath("bad_metadata.safetensors");
  WriteRawFile(path, R"({"__metadata__":{"format":1}})", 0);
  ExpectCorrupt(path, {"__metadata__", "format"});
  const std::string path2 = TempPath("bad_metadata2.safetensors");
  WriteRawFile(path2, R"({"__metadata__":"pt"})", 0);
  ExpectCorrupt(path2, {"__metadata__"});
}

}  // namespace
}  // namespace fd::model

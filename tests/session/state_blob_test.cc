#include "session/state_blob.h"

#include <cstdint>
#include <cstring>
#include <string>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "session/state_blob_format.h"
#include "tests/session/session_test_util.h"

namespace fd::session {
namespace {

using ::fd::session::testing::MakeImage;
using ::fd::session::testing::MakeSettings;
using ::testing::HasSubstr;

// Field offsets for a blob whose environment name has `env` bytes (see the
// layout in state_blob_format.h).
struct Offsets {
  explicit Offsets(size_t env) : environment(10), width(10 + env) {}
  size_t environment;
  size_t width;
  size_t height() const { return width + 4; }
  size_t scheduler() const { return width + 4 + 4 + 8 + 4; }
  size_t start_mode() const { return scheduler() + 4 + 4; }
  size_t has_previous_frame() const { return start_mode() + 1 + 8 + 1 + 8; }
  size_t pixel_bytes() const { return has_previous_frame() + 2; }
  size_t compressed_bytes() const { return pixel_bytes() + 8; }
  size_t pixels() const { return compressed_bytes() + 8; }
};

template <typename T>
void Poke(std::string& blob, size_t offset, T value) {
  for (size_t i = 0; i < sizeof(T); ++i) blob[offset + i] = static_cast<char>(value >> (8 * i));
}

template <typename T>
T Peek(const std::string& blob, size_t offset) {
  T value = 0;
  for (size_t i = 0; i < sizeof(T); ++i) {
    value |= static_cast<T>(static_cast<uint8_t>(blob[offset + i])) << (8 * i);
  }
  return value;
}

// Recomputes the trailing checksum after a test edited a field, so that the
// field's own validation is what rejects the blob.
void Reseal(std::string& blob) {
  const size_t body = blob.size() - kStateBlobChecksumBytes;
  Poke<uint64_t>(blob, body, StateBlobChecksum(std::string_view(blob).substr(0, body)));
}

SessionState RenderedState(const SessionSettings& s, int frames) {
  SessionState state = *SessionState::StartFromKeyframe(s, MakeImage(s, 1), MakeImage(s, 2));
  for (int i = 0; i < frames; ++i) {
    EXPECT_TRUE(state.CommitFrame(100 + i, MakeImage(s, 10 + i), MakeImage(s, 20 + i)).ok());
  }
  return state;
}

void ExpectRoundTrip(const SessionState& state) {
  absl::StatusOr<std::string> blob = ExportState(state);
  ASSERT_TRUE(blob.ok()) << blob.status();
  absl::StatusOr<SessionState> imported = ImportState(*blob);
  ASSERT_TRUE(imported.ok()) << imported.status();
  EXPECT_EQ(*imported, state);
  EXPECT_EQ(imported->settings(), state.settings());
  EXPECT_EQ(imported->NextFrameSeed(), state.NextFrameSeed());
  // Export is deterministic: the same state gives the same bytes.
  EXPECT_EQ(*ExportState(*imported), *blob);
}

TEST(StateBlobTest, RoundTripEveryShape) {
  const SessionSettings s = MakeSettings();
  ExpectRoundTrip(*SessionState::StartFromGBufferOnly(s));                    // no pixels
  ExpectRoundTrip(*SessionState::StartFromKeyframe(s, MakeImage(s, 1), {}));  // frame only
  ExpectRoundTrip(*SessionState::StartFromKeyframe(s, MakeImage(s, 1), MakeImage(s, 2)));
  ExpectRoundTrip(RenderedState(s, 3));
  SessionSettings other = MakeSettings("hillside", 24, 8, UINT64_MAX);
  other.scheduler = SchedulerKind::kEulerDiscrete;
  other.sky_mode = SkyMode::kClientImage;
  other.output_dtype = OutputDType::kFloat32;
  other.output_compression = OutputCompression::kNone;
  other.steps = 50;
  other.max_frames_in_flight = 7;
  ExpectRoundTrip(RenderedState(other, 1));
}

TEST(StateBlobTest, CompactAt512) {
  const SessionSettings s = MakeSettings("downtown_west", 512, 512);
  // A smooth image, like a rendered frame, compresses well; noise would not.
  ImageBuffer smooth(512, 512, 3, PixelType::kUint8);
  uint8_t* pixels = smooth.mutable_data();
  for (size_t i = 0; i < smooth.size_bytes(); ++i) {
    pixels[i] = static_cast<uint8_t>((i / 3) % 512 / 2);
  }
  SessionState state = *SessionState::StartFromKeyframe(s, smooth, smooth);
  absl::StatusOr<std::string> blob = ExportState(state);
  ASSERT_TRUE(blob.ok());
  EXPECT_LT(blob->size(), 2u * smooth.size_bytes() / 10) << blob->size() << " bytes";
  EXPECT_EQ(*ImportState(*blob), state);
}

class StateBlobCorruptionTest : public ::testing::Test {
 protected:
  void SetUp() override {
    settings_ = MakeSettings();
    state_ = RenderedState(settings_, 2);
    blob_ = *ExportState(state_);
    at_ = Offsets(settings_.environment.size());
    ASSERT_TRUE(ImportState(blob_).ok());
  }

  absl::Status Import(const std::string& blob) { return ImportState(blob).status(); }

  SessionSettings settings_;
  SessionState state_ = testing::MakeGBufferOnlyState();
  std::string blob_;
  Offsets at_{0};
};

TEST_F(StateBlobCorruptionTest, BadMagic) {
  std::string blob = blob_;
  blob[0] = 'X';
  absl::Status status = Import(blob);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(status.message(), HasSubstr("magic"));
  EXPECT_THAT(Import("").message(), HasSubstr("truncated at magic"));
  EXPECT_THAT(Import("definitely not a state blob").message(), HasSubstr("magic"));
}

TEST_F(StateBlobCorruptionTest, UnsupportedVersion) {
  std::string blob = blob_;
  Poke<uint16_t>(blob, 4, 2);
  absl::Status status = Import(blob);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(status.message(), HasSubstr("version: unsupported version 2"));
  Poke<uint16_t>(blob, 4, 0);
  EXPECT_THAT(Import(blob).message(), HasSubstr("unsupported version 0"));
}

TEST_F(StateBlobCorruptionTest, ReservedFlags) {
  std::string blob = blob_;
  Poke<uint16_t>(blob, 6, 1);
  EXPECT_THAT(Import(blob).message(), HasSubstr("flags"));
}

// Every proper prefix is rejected as truncated, naming the field it cut.
TEST_F(StateBlobCorruptionTest, TruncatedAnywhere) {
  for (size_t length = 0; length < blob_.size(); ++length) {
    absl::Status status = Import(blob_.substr(0, length));
    ASSERT_EQ(status.code(), absl::StatusCode::kInvalidArgument) << length;
    ASSERT_THAT(status.message(), HasSubstr("truncated at")) << length;
  }
  EXPECT_THAT(Import(blob_.substr(0, at_.width + 2)).message(), HasSubstr("truncated at width"));
  EXPECT_THAT(Import(blob_.substr(0, at_.pixels() + 10)).message(),
              HasSubstr("truncated at pixels"));
  EXPECT_THAT(Import(blob_.substr(0, blob_.size() - 1)).message(),
              HasSubstr("truncated at checksum"));
}

TEST_F(StateBlobCorruptionTest, TrailingBytes) {
  EXPECT_THAT(Import(blob_ + "x").message(), HasSubstr("1 unexpected bytes after the checksum"));
}

// Flipping any single byte is detected (by a field check or the checksum).
TEST_F(StateBlobCorruptionTest, AnyFlippedByteIsRejected) {
  for (size_t i = 0; i < blob_.size(); ++i) {
    std::string blob = blob_;
    blob[i] = static_cast<char>(blob[i] ^ 0x20);
    ASSERT_EQ(Import(blob).code(), absl::StatusCode::kInvalidArgument) << "byte " << i;
  }
  std::string blob = blob_;
  blob[at_.pixels() + 20] ^= 1;
  EXPECT_THAT(Import(blob).message(), HasSubstr("checksum: mismatch"));
}

TEST_F(StateBlobCorruptionTest, SizeMismatch) {
  // The settings say 64x32 but the blob holds pixels for another size.
  std::string blob = blob_;
  Poke<uint32_t>(blob, at_.width, settings_.width * 2);
  Reseal(blob);
  absl::Status status = Import(blob);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(status.message(), HasSubstr("pixel_bytes: expected 24576"));

  // pixel_bytes consistent with the settings but not with the zstd frame.
  blob = blob_;
  Poke<uint8_t>(blob, at_.has_previous_frame() + 1, 0);  // drop the basecolor
  Poke<uint64_t>(blob, at_.pixel_bytes(), settings_.width * settings_.height * 3);
  Reseal(blob);
  EXPECT_THAT(Import(blob).message(), HasSubstr("the zstd frame holds 12288 bytes"));

  // A width beyond kMaxImageSide is refused before anything is allocated.
  blob = blob_;
  Poke<uint32_t>(blob, at_.width, kMaxImageSide + 1);
  Reseal(blob);
  EXPECT_THAT(Import(blob).message(), HasSubstr("settings.width"));
}

TEST_F(StateBlobCorruptionTest, BadZstdData) {
  std::string blob = blob_;
  // Overwrite the zstd frame's magic number.
  Poke<uint32_t>(blob, at_.pixels(), 0xdeadbeef);
  Reseal(blob);
  absl::Status status = Import(blob);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(status.message(), HasSubstr("pixels: not a zstd frame"));

  // Damage inside the compressed block: zstd's own checksum or decoder fails.
  blob = blob_;
  const size_t compressed = Peek<uint64_t>(blob, at_.compressed_bytes());
  ASSERT_GT(compressed, 40u);
  blob[at_.pixels() + compressed / 2] ^= 0x55;
  Reseal(blob);
  EXPECT_THAT(Import(blob).message(), HasSubstr("pixels: zstd: "));
}

TEST_F(StateBlobCorruptionTest, InvalidFieldValues) {
  std::string blob = blob_;
  Poke<uint8_t>(blob, at_.scheduler(), 9);
  Reseal(blob);
  EXPECT_THAT(Import(blob).message(), HasSubstr("settings.scheduler: invalid value 9"));

  blob = blob_;
  Poke<uint8_t>(blob, at_.start_mode(), 0);
  Reseal(blob);
  EXPECT_THAT(Import(blob).message(), HasSubstr("start_mode: invalid value 0"));

  blob = blob_;
  Poke<uint8_t>(blob, at_.has_previous_frame(), 2);
  Reseal(blob);
  EXPECT_THAT(Import(blob).message(), HasSubstr("has_previous_frame: must be 0 or 1, got 2"));

  blob = blob_;
  Poke<uint16_t>(blob, 8, kMaxEnvironmentNameBytes + 1);
  EXPECT_THAT(Import(blob).message(), HasSubstr("environment_length: at most 256"));
}

}  // namespace
}  // namespace fd::session

#include "session/state_blob.h"

#include <zstd.h>

#include <cstring>
#include <memory>
#include <optional>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/types/span.h"
#include "session/state_blob_format.h"

namespace fd::session {
namespace {

// zstd level 3 (its default): a 512x512 state compresses in a few ms, and
// export is rare (resume elsewhere), so there is no reason to trade size.
constexpr int kZstdLevel = 3;

// Appends little-endian integers and raw bytes.
class BlobWriter {
 public:
  template <typename T>
  void Put(T value) {
    static_assert(std::is_unsigned_v<T>);
    for (size_t i = 0; i < sizeof(T); ++i) {
      out_.push_back(static_cast<char>((value >> (8 * i)) & 0xff));
    }
  }
  void PutBytes(std::string_view bytes) { out_.append(bytes); }
  std::string& out() { return out_; }

 private:
  std::string out_;
};

// Reads what BlobWriter wrote; every read names its field so that a short
// blob is reported as "state blob truncated at <field>".
class BlobReader {
 public:
  explicit BlobReader(std::string_view blob) : blob_(blob) {}

  template <typename T>
  absl::Status Get(const char* field, T* value) {
    static_assert(std::is_unsigned_v<T>);
    absl::Status available = Need(field, sizeof(T));
    if (!available.ok()) return available;
    T v = 0;
    for (size_t i = 0; i < sizeof(T); ++i) {
      v |= static_cast<T>(static_cast<uint8_t>(blob_[offset_ + i])) << (8 * i);
    }
    offset_ += sizeof(T);
    *value = v;
    return absl::OkStatus();
  }

  absl::Status GetBytes(const char* field, size_t size, std::string_view* bytes) {
    absl::Status available = Need(field, size);
    if (!available.ok()) return available;
    *bytes = blob_.substr(offset_, size);
    offset_ += size;
    return absl::OkStatus();
  }

  size_t offset() const { return offset_; }
  size_t remaining() const { return blob_.size() - offset_; }

 private:
  absl::Status Need(const char* field, size_t size) const {
    if (size > remaining()) {
      return absl::InvalidArgumentError(absl::StrCat("state blob truncated at ", field, ": needs ",
                                                     size, " bytes at offset ", offset_,
                                                     ", the blob has ", blob_.size(), " bytes"));
    }
    return absl::OkStatus();
  }

  std::string_view blob_;
  size_t offset_ = 0;
};

// Reads a 0/1 byte into a bool; INVALID_ARGUMENT for any other value.
absl::Status GetFlag(BlobReader& reader, const char* field, bool* flag) {
  uint8_t byte = 0;
  absl::Status read = reader.Get(field, &byte);
  if (!read.ok()) return read;
  if (byte > 1) {
    return absl::InvalidArgumentError(
        absl::StrCat("state blob ", field, ": must be 0 or 1, got ", static_cast<int>(byte)));
  }
  *flag = byte == 1;
  return absl::OkStatus();
}

struct ZstdCCtxDeleter {
  void operator()(ZSTD_CCtx* ctx) const { ZSTD_freeCCtx(ctx); }
};

absl::StatusOr<std::string> Compress(absl::Span<const uint8_t> a, absl::Span<const uint8_t> b) {
  std::unique_ptr<ZSTD_CCtx, ZstdCCtxDeleter> ctx(ZSTD_createCCtx());
  if (ctx == nullptr) return absl::InternalError("state blob: ZSTD_createCCtx failed");
  size_t rc = ZSTD_CCtx_setParameter(ctx.get(), ZSTD_c_compressionLevel, kZstdLevel);
  if (!ZSTD_isError(rc)) rc = ZSTD_CCtx_setParameter(ctx.get(), ZSTD_c_checksumFlag, 1);
  if (!ZSTD_isError(rc)) rc = ZSTD_CCtx_setParameter(ctx.get(), ZSTD_c_contentSizeFlag, 1);
  if (!ZSTD_isError(rc)) rc = ZSTD_CCtx_setPledgedSrcSize(ctx.get(), a.size() + b.size());
  if (ZSTD_isError(rc)) {
    return absl::InternalError(absl::StrCat("state blob: zstd setup: ", ZSTD_getErrorName(rc)));
  }
  // Stream both buffers into one frame without concatenating them first.
  std::string out(ZSTD_compressBound(a.size() + b.size()), '\0');
  ZSTD_outBuffer output{out.data(), out.size(), 0};
  const absl::Span<const uint8_t> parts[] = {a, b};
  for (int i = 0; i < 2; ++i) {
    ZSTD_inBuffer input{parts[i].data(), parts[i].size(), 0};
    const ZSTD_EndDirective mode = i == 1 ? ZSTD_e_end : ZSTD_e_continue;
    size_t remaining = 0;
    do {
      remaining = ZSTD_compressStream2(ctx.get(), &output, &input, mode);
      if (ZSTD_isError(remaining)) {
        return absl::InternalError(
            absl::StrCat("state blob: zstd compress: ", ZSTD_getErrorName(remaining)));
      }
    } while (mode == ZSTD_e_end ? remaining != 0 : input.pos < input.size);
  }
  out.resize(output.pos);
  return out;
}

}  // namespace

absl::StatusOr<std::string> ExportState(const SessionState& state) {
  const SessionSettings& s = state.settings();
  BlobWriter w;
  w.PutBytes(kStateBlobMagic);
  w.Put<uint16_t>(kStateBlobVersion);
  w.Put<uint16_t>(0);  // flags
  if (s.environment.size() > kMaxEnvironmentNameBytes) {
    // Unreachable for names the server accepts; checked so import never fails
    // on a blob export wrote.
    return absl::InvalidArgumentError(
        absl::StrCat("settings.environment: longer than ", kMaxEnvironmentNameBytes, " bytes"));
  }
  w.Put<uint16_t>(static_cast<uint16_t>(s.environment.size()));
  w.PutBytes(s.environment);
  w.Put<uint32_t>(s.width);
  w.Put<uint32_t>(s.height);
  w.Put<uint64_t>(s.seed);
  w.Put<uint32_t>(s.steps);
  w.Put<uint8_t>(static_cast<uint8_t>(s.scheduler));
  w.Put<uint8_t>(static_cast<uint8_t>(s.sky_mode));
  w.Put<uint8_t>(static_cast<uint8_t>(s.output_dtype));
  w.Put<uint8_t>(static_cast<uint8_t>(s.output_compression));
  w.Put<uint32_t>(s.max_frames_in_flight);
  w.Put<uint8_t>(static_cast<uint8_t>(state.start_mode()));
  w.Put<uint64_t>(state.frame_counter());
  w.Put<uint8_t>(state.last_frame_index().has_value() ? 1 : 0);
  w.Put<uint64_t>(state.last_frame_index().value_or(0));
  w.Put<uint8_t>(state.has_previous_frame() ? 1 : 0);
  w.Put<uint8_t>(state.has_previous_basecolor() ? 1 : 0);
  const uint64_t pixel_bytes =
      state.previous_frame().size_bytes() + state.previous_basecolor().size_bytes();
  w.Put<uint64_t>(pixel_bytes);
  std::string compressed;
  if (pixel_bytes > 0) {
    absl::StatusOr<std::string> packed =
        Compress(state.previous_frame().bytes(), state.previous_basecolor().bytes());
    if (!packed.ok()) return packed.status();
    compressed = *std::move(packed);
  }
  w.Put<uint64_t>(compressed.size());
  w.PutBytes(compressed);
  w.Put<uint64_t>(StateBlobChecksum(w.out()));
  return std::move(w.out());
}

absl::StatusOr<SessionState> ImportState(std::string_view blob) {
  BlobReader r(blob);
#define FD_BLOB_READ(expr)                             \
  do {                                                 \
    absl::Status fd_blob_status_ = (expr);             \
    if (!fd_blob_status_.ok()) return fd_blob_status_; \
  } while (false)

  std::string_view magic;
  FD_BLOB_READ(r.GetBytes("magic", kStateBlobMagic.size(), &magic));
  if (magic != kStateBlobMagic) {
    return absl::InvalidArgumentError(
        "state blob magic: not a FrameDiffuser session state (expected \"FDSS\")");
  }
  uint16_t version = 0;
  FD_BLOB_READ(r.Get("version", &version));
  if (version != kStateBlobVersion) {
    return absl::InvalidArgumentError(absl::StrCat("state blob version: unsupported version ",
                                                   version, " (this server reads version ",
                                                   kStateBlobVersion, ")"));
  }
  uint16_t flags = 0;
  FD_BLOB_READ(r.Get("flags", &flags));
  if (flags != 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("state blob flags: reserved, must be 0, got ", flags));
  }

  SessionSettings s;
  uint16_t environment_length = 0;
  FD_BLOB_READ(r.Get("environment_length", &environment_length));
  if (environment_length > kMaxEnvironmentNameBytes) {
    return absl::InvalidArgumentError(absl::StrCat("state blob environment_length: at most ",
                                                   kMaxEnvironmentNameBytes, ", got ",
                                                   environment_length));
  }
  std::string_view environment;
  FD_BLOB_READ(r.GetBytes("environment", environment_length, &environment));
  s.environment = std::string(environment);
  FD_BLOB_READ(r.Get("width", &s.width));
  FD_BLOB_READ(r.Get("height", &s.height));
  FD_BLOB_READ(r.Get("seed", &s.seed));
  FD_BLOB_READ(r.Get("steps", &s.steps));
  uint8_t scheduler = 0, sky_mode = 0, output_dtype = 0, output_compression = 0, start_mode = 0;
  FD_BLOB_READ(r.Get("scheduler", &scheduler));
  FD_BLOB_READ(r.Get("sky_mode", &sky_mode));
  FD_BLOB_READ(r.Get("output_dtype", &output_dtype));
  FD_BLOB_READ(r.Get("output_compression", &output_compression));
  // Enum values are range-checked by SessionState::Restore below.
  s.scheduler = static_cast<SchedulerKind>(scheduler);
  s.sky_mode = static_cast<SkyMode>(sky_mode);
  s.output_dtype = static_cast<OutputDType>(output_dtype);
  s.output_compression = static_cast<OutputCompression>(output_compression);
  FD_BLOB_READ(r.Get("max_frames_in_flight", &s.max_frames_in_flight));
  FD_BLOB_READ(r.Get("start_mode", &start_mode));
  uint64_t frame_counter = 0, last_frame_index = 0;
  bool has_last_frame_index = false, has_previous_frame = false, has_previous_basecolor = false;
  FD_BLOB_READ(r.Get("frame_counter", &frame_counter));
  FD_BLOB_READ(GetFlag(r, "has_last_frame_index", &has_last_frame_index));
  FD_BLOB_READ(r.Get("last_frame_index", &last_frame_index));
  FD_BLOB_READ(GetFlag(r, "has_previous_frame", &has_previous_frame));
  FD_BLOB_READ(GetFlag(r, "has_previous_basecolor", &has_previous_basecolor));
  uint64_t pixel_bytes = 0, compressed_bytes = 0;
  FD_BLOB_READ(r.Get("pixel_bytes", &pixel_bytes));
  FD_BLOB_READ(r.Get("compressed_bytes", &compressed_bytes));
  std::string_view compressed;
  FD_BLOB_READ(r.GetBytes("pixels", compressed_bytes, &compressed));
  const size_t checksummed = r.offset();
  uint64_t checksum = 0;
  FD_BLOB_READ(r.Get("checksum", &checksum));
#undef FD_BLOB_READ
  if (r.remaining() != 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("state blob: ", r.remaining(), " unexpected bytes after the checksum"));
  }
  if (checksum != StateBlobChecksum(blob.substr(0, checksummed))) {
    return absl::InvalidArgumentError("state blob checksum: mismatch (the blob is corrupted)");
  }

  // Sizes: the settings decide how many pixel bytes there must be. Checked
  // before anything is allocated; ValidateSessionSettings bounds width and
  // height by kMaxImageSide.
  absl::Status valid = ValidateSessionSettings(s);
  if (!valid.ok()) {
    return absl::InvalidArgumentError(absl::StrCat("state blob ", valid.message()));
  }
  const uint64_t image_bytes = static_cast<uint64_t>(s.width) * s.height * 3;
  const uint64_t expected_pixel_bytes =
      image_bytes * ((has_previous_frame ? 1 : 0) + (has_previous_basecolor ? 1 : 0));
  if (pixel_bytes != expected_pixel_bytes) {
    return absl::InvalidArgumentError(absl::StrCat(
        "state blob pixel_bytes: expected ", expected_pixel_bytes, " (", s.width, " x ", s.height,
        " x 3 x ", expected_pixel_bytes / (image_bytes == 0 ? 1 : image_bytes), " images), got ",
        pixel_bytes));
  }
  if ((pixel_bytes == 0) != (compressed_bytes == 0)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "state blob compressed_bytes: ", compressed_bytes, " for ", pixel_bytes, " pixel bytes"));
  }

  ImageBuffer previous_frame, previous_basecolor;
  if (pixel_bytes > 0) {
    const unsigned long long content_size =
        ZSTD_getFrameContentSize(compressed.data(), compressed.size());
    if (content_size == ZSTD_CONTENTSIZE_ERROR) {
      return absl::InvalidArgumentError("state blob pixels: not a zstd frame");
    }
    if (content_size != pixel_bytes) {
      return absl::InvalidArgumentError(absl::StrCat("state blob pixels: the zstd frame holds ",
                                                     content_size == ZSTD_CONTENTSIZE_UNKNOWN
                                                         ? std::string("an unknown number of")
                                                         : absl::StrCat(content_size),
                                                     " bytes, pixel_bytes says ", pixel_bytes));
    }
    std::vector<uint8_t> pixels(pixel_bytes);
    const size_t rc =
        ZSTD_decompress(pixels.data(), pixels.size(), compressed.data(), compressed.size());
    if (ZSTD_isError(rc)) {
      return absl::InvalidArgumentError(
          absl::StrCat("state blob pixels: zstd: ", ZSTD_getErrorName(rc)));
    }
    if (rc != pixel_bytes) {
      return absl::InvalidArgumentError(absl::StrCat("state blob pixels: decompressed to ", rc,
                                                     " bytes, expected ", pixel_bytes));
    }
    // image_bytes = width * height * 3 was checked against pixel_bytes above.
    auto image = [&](const uint8_t* from) {
      ImageBuffer out(s.width, s.height, 3, PixelType::kUint8);
      std::memcpy(out.mutable_data(), from, image_bytes);
      return out;
    };
    if (has_previous_frame) previous_frame = image(pixels.data());
    if (has_previous_basecolor)
      previous_basecolor = image(pixels.data() + pixels.size() - image_bytes);
  }

  std::optional<uint64_t> last;
  if (has_last_frame_index) last = last_frame_index;
  absl::StatusOr<SessionState> state =
      SessionState::Restore(std::move(s), static_cast<StartMode>(start_mode), frame_counter, last,
                            std::move(previous_frame), std::move(previous_basecolor));
  if (!state.ok()) {
    return absl::InvalidArgumentError(absl::StrCat("state blob ", state.status().message()));
  }
  return state;
}

}  // namespace fd::session

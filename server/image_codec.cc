#include "server/image_codec.h"

#include <zstd.h>
#include <zstd_errors.h>

#include <cmath>
#include <cstring>
#include <memory>
#include <string>

#include "absl/strings/str_cat.h"
#include "base/status_macros.h"

namespace fd::server {
namespace {

// Wire floats are little endian; we copy them with memcpy.
static_assert(__BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__,
              "image_codec assumes a little-endian host");

// Level 1: rendered frames are compressed once per frame on the response
// path, where latency matters more than the last few percent of size.
constexpr int kZstdLevel = 1;

struct ZstdCCtxDeleter {
  void operator()(ZSTD_CCtx* ctx) const { ZSTD_freeCCtx(ctx); }
};
struct ZstdDCtxDeleter {
  void operator()(ZSTD_DCtx* ctx) const { ZSTD_freeDCtx(ctx); }
};

// One context per thread: creating one per image costs an allocation of
// several hundred KiB; the contexts hold no state between calls.
ZSTD_CCtx* ThreadCCtx() {
  thread_local std::unique_ptr<ZSTD_CCtx, ZstdCCtxDeleter> ctx(ZSTD_createCCtx());
  return ctx.get();
}
ZSTD_DCtx* ThreadDCtx() {
  thread_local std::unique_ptr<ZSTD_DCtx, ZstdDCtxDeleter> ctx(ZSTD_createDCtx());
  return ctx.get();
}

size_t ElementSize(v1::DType dtype) {
  switch (dtype) {
    case v1::DTYPE_UINT8:
      return 1;
    case v1::DTYPE_FLOAT16:
      return 2;
    case v1::DTYPE_FLOAT32:
      return 4;
    default:
      return 0;
  }
}

absl::Status FieldError(std::string_view field, std::string_view sub, std::string_view what) {
  return absl::InvalidArgumentError(
      absl::StrCat(std::string(field), ".", std::string(sub), ": ", std::string(what)));
}

absl::Status CheckDim(std::string_view field, std::string_view name, uint32_t expected,
                      uint32_t got) {
  if (got == expected) return absl::OkStatus();
  return FieldError(field, name, absl::StrCat("expected ", expected, ", got ", got));
}

// Shape, dtype and compression; returns the decoded payload's byte count.
absl::StatusOr<size_t> CheckHeader(const v1::Image& image, std::string_view field,
                                   const ImageShape& expected) {
  FD_RETURN_IF_ERROR(CheckDim(field, "width", expected.width, image.width()));
  FD_RETURN_IF_ERROR(CheckDim(field, "height", expected.height, image.height()));
  FD_RETURN_IF_ERROR(CheckDim(field, "channels", expected.channels, image.channels()));
  if (image.dtype() == v1::DTYPE_UNSPECIFIED) return FieldError(field, "dtype", "must be set");
  const size_t element = ElementSize(image.dtype());
  if (element == 0) {
    return FieldError(field, "dtype",
                      absl::StrCat("unknown value ", static_cast<int>(image.dtype())));
  }
  if (image.compression() != v1::COMPRESSION_NONE && image.compression() != v1::COMPRESSION_ZSTD) {
    return FieldError(field, "compression",
                      absl::StrCat("unknown value ", static_cast<int>(image.compression())));
  }
  return size_t{expected.width} * expected.height * expected.channels * element;
}

// Decompresses image.data (one zstd frame) into exactly `bytes` bytes at dst.
absl::Status Decompress(const v1::Image& image, std::string_view field, size_t bytes, char* dst) {
  const std::string& data = image.data();
  const unsigned long long content = ZSTD_getFrameContentSize(data.data(), data.size());
  if (content == ZSTD_CONTENTSIZE_ERROR) {
    return FieldError(field, "data",
                      absl::StrCat("zstd: not a zstd frame (", data.size(), " bytes)"));
  }
  // Checked before decompressing anything: a frame that says it is larger
  // than the image is rejected at the cost of reading its header.
  if (content != ZSTD_CONTENTSIZE_UNKNOWN && content != bytes) {
    return FieldError(field, "data",
                      absl::StrCat("zstd frame declares ", content, " bytes, expected ", bytes));
  }
  const size_t frame = ZSTD_findFrameCompressedSize(data.data(), data.size());
  if (ZSTD_isError(frame)) {
    return FieldError(field, "data", absl::StrCat("zstd: ", ZSTD_getErrorName(frame)));
  }
  if (frame != data.size()) {
    return FieldError(field, "data",
                      absl::StrCat("zstd: ", data.size() - frame,
                                   " bytes after the first frame (send exactly one frame)"));
  }
  ZSTD_DCtx* ctx = ThreadDCtx();
  if (ctx == nullptr)
    return absl::InternalError(absl::StrCat(std::string(field), ": ZSTD_createDCtx failed"));
  // Single-pass decompression writes only into dst, so a frame without a
  // content size cannot expand past `bytes`: it fails with dstSize_tooSmall.
  const size_t got = ZSTD_decompressDCtx(ctx, dst, bytes, data.data(), data.size());
  if (ZSTD_isError(got)) {
    if (ZSTD_getErrorCode(got) == ZSTD_error_dstSize_tooSmall) {
      return FieldError(field, "data",
                        absl::StrCat("zstd frame decompresses to more than ", bytes, " bytes"));
    }
    return FieldError(field, "data", absl::StrCat("zstd: ", ZSTD_getErrorName(got)));
  }
  if (got != bytes) {
    return FieldError(field, "data",
                      absl::StrCat("zstd frame holds ", got, " bytes, expected ", bytes));
  }
  return absl::OkStatus();
}

// The raw elements of the payload: a view of image.data when uncompressed,
// else decompressed into `storage`.
absl::StatusOr<const char*> RawElements(const v1::Image& image, std::string_view field,
                                        size_t bytes, std::string* storage) {
  if (image.compression() == v1::COMPRESSION_NONE) {
    if (image.data().size() != bytes) {
      return FieldError(field, "data",
                        absl::StrCat("expected ", bytes, " bytes, got ", image.data().size()));
    }
    return image.data().data();
  }
  storage->resize(bytes);
  FD_RETURN_IF_ERROR(Decompress(image, field, bytes, storage->data()));
  return storage->data();
}

absl::Status NonFinite(std::string_view field, const ImageShape& shape, size_t index, bool nan) {
  const size_t pixel = index / shape.channels;
  return FieldError(field, "data",
                    absl::StrCat(nan ? "NaN" : "Inf", " at pixel (", pixel % shape.width, ", ",
                                 pixel / shape.width, ") channel ", index % shape.channels));
}

float Clamp01(float value) {
  // !(v > 0) also maps -0.0 to +0.0.
  if (!(value > 0.0f)) return 0.0f;
  return value > 1.0f ? 1.0f : value;
}

// Writes the payload's shape.width*height*channels floats, validated and
// clamped, to dst. The header must have been checked (dtype is float).
absl::Status DecodeFloats(const v1::Image& image, std::string_view field, const ImageShape& shape,
                          size_t bytes, float* dst) {
  std::string storage;
  FD_ASSIGN_OR_RETURN(const char* raw, RawElements(image, field, bytes, &storage));
  const size_t count = bytes / ElementSize(image.dtype());
  if (image.dtype() == v1::DTYPE_FLOAT32) {
    std::memcpy(dst, raw, bytes);
    for (size_t i = 0; i < count; ++i) {
      if (!std::isfinite(dst[i])) return NonFinite(field, shape, i, std::isnan(dst[i]));
      dst[i] = Clamp01(dst[i]);
    }
    return absl::OkStatus();
  }
  const auto* in = reinterpret_cast<const unsigned char*>(raw);
  for (size_t i = 0; i < count; ++i) {
    const uint16_t bits = static_cast<uint16_t>(in[2 * i] | (in[2 * i + 1] << 8));
    if ((bits & 0x7C00u) == 0x7C00u) return NonFinite(field, shape, i, (bits & 0x03FFu) != 0);
    dst[i] = Clamp01(HalfBitsToFloat(bits));
  }
  return absl::OkStatus();
}

std::string SizeError(std::string_view name, size_t expected, size_t got) {
  return absl::StrCat("EncodeImage: ", std::string(name), ": expected ", expected, " values, got ",
                      got);
}

}  // namespace

// IEEE 754 binary32 -> binary16, round to nearest even (the same results
// as c10::Half / the FP16 library, written out so the codec needs no
// LibTorch). Overflow gives +-Inf; NaN stays a (quiet) NaN.
uint16_t FloatToHalfBits(float value) {
  uint32_t f;
  std::memcpy(&f, &value, sizeof(f));
  const uint16_t sign = static_cast<uint16_t>((f >> 16) & 0x8000u);
  const uint32_t abs = f & 0x7FFFFFFFu;
  if (abs > 0x7F800000u) return static_cast<uint16_t>(sign | 0x7E00u);   // NaN
  if (abs >= 0x477FF000u) return static_cast<uint16_t>(sign | 0x7C00u);  // rounds to Inf
  if (abs < 0x38800000u) {
    // Subnormal half (or zero): the value in units of 2^-24, rounded to
    // nearest even; done in float arithmetic, which is exact here.
    if (abs < 0x33000000u) return sign;  // below half the smallest subnormal
    float magnitude;
    std::memcpy(&magnitude, &abs, sizeof(magnitude));
    const float units = std::nearbyint(magnitude * 16777216.0f);  // 2^24
    return static_cast<uint16_t>(sign | static_cast<uint16_t>(units));
  }
  // Normal: rebias the exponent and round the 13 dropped mantissa bits.
  const uint32_t rebased = abs - 0x38000000u;  // exponent bias 127 -> 15
  const uint32_t lsb = (rebased >> 13) & 1u;
  const uint32_t rounded = rebased + 0x0FFFu + lsb;
  return static_cast<uint16_t>(sign | (rounded >> 13));
}

float HalfBitsToFloat(uint16_t bits) {
  const uint32_t sign = static_cast<uint32_t>(bits & 0x8000u) << 16;
  const uint32_t exponent = (bits >> 10) & 0x1Fu;
  const uint32_t mantissa = bits & 0x03FFu;
  uint32_t f;
  if (exponent == 0x1Fu) {
    f = sign | 0x7F800000u | (mantissa << 13);  // Inf / NaN
  } else if (exponent != 0) {
    f = sign | ((exponent + 112u) << 23) | (mantissa << 13);
  } else if (mantissa == 0) {
    f = sign;
  } else {
    // Subnormal: mantissa * 2^-24, exact in float.
    const float magnitude = static_cast<float>(mantissa) * (1.0f / 16777216.0f);
    std::memcpy(&f, &magnitude, sizeof(f));
    f |= sign;
  }
  float value;
  std::memcpy(&value, &f, sizeof(value));
  return value;
}

absl::StatusOr<ImageBuffer> DecodeImage(const v1::Image& image, std::string_view field,
                                        const ImageShape& expected) {
  FD_ASSIGN_OR_RETURN(const size_t bytes, CheckHeader(image, field, expected));
  // Sizes were checked against `expected` before this allocation.
  if (image.dtype() == v1::DTYPE_UINT8) {
    ImageBuffer out(expected.width, expected.height, expected.channels, PixelType::kUint8);
    char* dst = reinterpret_cast<char*>(out.mutable_data());
    if (image.compression() == v1::COMPRESSION_ZSTD) {
      FD_RETURN_IF_ERROR(Decompress(image, field, bytes, dst));
    } else {
      std::string unused;
      FD_ASSIGN_OR_RETURN(const char* raw, RawElements(image, field, bytes, &unused));
      std::memcpy(dst, raw, bytes);
    }
    return out;
  }
  ImageBuffer out(expected.width, expected.height, expected.channels, PixelType::kFloat32);
  FD_RETURN_IF_ERROR(DecodeFloats(image, field, expected, bytes, out.mutable_floats()));
  return out;
}

absl::StatusOr<ImageBuffer> DecodeImageBytes(const v1::Image& image, std::string_view field,
                                             const ImageShape& expected) {
  FD_ASSIGN_OR_RETURN(ImageBuffer decoded, DecodeImage(image, field, expected));
  if (decoded.type() == PixelType::kUint8) return decoded;
  const absl::Span<const float> floats = decoded.float_elements();
  ImageBuffer out(expected.width, expected.height, expected.channels, PixelType::kUint8);
  uint8_t* dst = out.mutable_data();
  for (size_t i = 0; i < floats.size(); ++i) {
    // Same arithmetic as session::BasecolorBuffer: float x * 255, rounded
    // half to even (the default rounding mode), in [0, 255] after clamping.
    dst[i] = static_cast<uint8_t>(std::nearbyint(floats[i] * 255.0f));
  }
  return out;
}

absl::Status EncodeImage(const ImageBuffer& image, session::OutputDType dtype,
                         session::OutputCompression compression, v1::Image* out) {
  const uint32_t width = image.width(), height = image.height();
  if (image.channels() != 3 && !image.empty()) {
    return absl::InvalidArgumentError(
        absl::StrCat("EncodeImage: expected 3 channels, got ", image.channels()));
  }
  const bool is_float = image.type() == PixelType::kFloat32;
  const absl::Span<const uint8_t> uint8_rgb =
      is_float ? absl::Span<const uint8_t>() : image.uint8_elements();
  const absl::Span<const float> float_rgb =
      is_float ? image.float_elements() : absl::Span<const float>();
  if (width == 0 || height == 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("EncodeImage: width and height must be > 0, got ", width, "x", height));
  }
  if (compression != session::OutputCompression::kNone &&
      compression != session::OutputCompression::kZstd) {
    return absl::InvalidArgumentError(
        absl::StrCat("EncodeImage: unknown compression ", static_cast<int>(compression)));
  }
  const size_t count = size_t{width} * height * 3;
  std::string raw;  // the elements, when they are not the caller's buffer
  const char* elements = nullptr;
  size_t bytes = 0;
  v1::DType wire_dtype = v1::DTYPE_UNSPECIFIED;
  switch (dtype) {
    case session::OutputDType::kUint8:
      if (uint8_rgb.size() != count) {
        return absl::InvalidArgumentError(SizeError("uint8_rgb", count, uint8_rgb.size()));
      }
      elements = reinterpret_cast<const char*>(uint8_rgb.data());
      bytes = count;
      wire_dtype = v1::DTYPE_UINT8;
      break;
    case session::OutputDType::kFloat32:
      if (float_rgb.size() != count) {
        return absl::InvalidArgumentError(SizeError("float_rgb", count, float_rgb.size()));
      }
      elements = reinterpret_cast<const char*>(float_rgb.data());
      bytes = count * sizeof(float);
      wire_dtype = v1::DTYPE_FLOAT32;
      break;
    case session::OutputDType::kFloat16: {
      if (float_rgb.size() != count) {
        return absl::InvalidArgumentError(SizeError("float_rgb", count, float_rgb.size()));
      }
      raw.resize(count * 2);
      for (size_t i = 0; i < count; ++i) {
        const uint16_t bits = FloatToHalfBits(float_rgb[i]);
        raw[2 * i] = static_cast<char>(bits & 0xFF);
        raw[2 * i + 1] = static_cast<char>(bits >> 8);
      }
      elements = raw.data();
      bytes = raw.size();
      wire_dtype = v1::DTYPE_FLOAT16;
      break;
    }
    default:
      return absl::InvalidArgumentError(
          absl::StrCat("EncodeImage: unknown dtype ", static_cast<int>(dtype)));
  }

  std::string data;
  if (compression == session::OutputCompression::kZstd) {
    ZSTD_CCtx* ctx = ThreadCCtx();
    if (ctx == nullptr) return absl::InternalError("EncodeImage: ZSTD_createCCtx failed");
    data.resize(ZSTD_compressBound(bytes));
    // ZSTD_compressCCtx writes the content size into the frame header.
    const size_t written =
        ZSTD_compressCCtx(ctx, data.data(), data.size(), elements, bytes, kZstdLevel);
    if (ZSTD_isError(written)) {
      return absl::InternalError(
          absl::StrCat("EncodeImage: zstd compression failed: ", ZSTD_getErrorName(written)));
    }
    data.resize(written);
  } else if (!raw.empty()) {
    data = std::move(raw);
  } else {
    data.assign(elements, bytes);
  }
  out->Clear();
  out->set_width(width);
  out->set_height(height);
  out->set_channels(3);
  out->set_dtype(wire_dtype);
  out->set_compression(compression == session::OutputCompression::kZstd ? v1::COMPRESSION_ZSTD
                                                                        : v1::COMPRESSION_NONE);
  out->set_data(std::move(data));
  return absl::OkStatus();
}

}  // namespace fd::server

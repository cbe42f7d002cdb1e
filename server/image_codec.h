// Wire images (framediffuser.v1.Image) <-> ImageBuffers (base/image_buffer.h).
// No LibTorch: the session layer turns the buffers into tensors.
//
// The one place that knows the wire encoding of an Image: dtypes (uint8,
// IEEE binary16, binary32, all little endian), optional zstd, and the checks a
// client's bytes must pass before anything else looks at them. Every error is
// INVALID_ARGUMENT and names the sub-field ("frame.gbuffer.depth.channels:
// expected 1, got 3"), so the server can forward it as a FrameError.
//
// Untrusted input: sizes are compared with what the field expects BEFORE any
// allocation, and a zstd frame can never make us write more than the
// expected number of bytes (no zip bombs).
#ifndef FD_SERVER_IMAGE_CODEC_H_
#define FD_SERVER_IMAGE_CODEC_H_

#include <cstdint>
#include <string_view>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/types/span.h"
#include "base/image_buffer.h"
#include "framediffuser/v1/image.pb.h"
#include "session/session_settings.h"

namespace fd::server {

namespace v1 = ::framediffuser::v1;

// What a field expects. Value type.
struct ImageShape {
  uint32_t width = 0;
  uint32_t height = 0;
  uint32_t channels = 0;
};

// Decodes and validates one wire Image held in field `field` (e.g.
// "frame.gbuffer.depth"). Returns a new HWC buffer of the expected shape:
// uint8 for DTYPE_UINT8, float32 for DTYPE_FLOAT16 / DTYPE_FLOAT32 (float16
// converted exactly). Finite float values outside [0, 1] are clamped to
// [0, 1] (fp16 rounding makes e.g. 1.0009766 common).
//
// INVALID_ARGUMENT, naming the sub-field, for: a width/height/channels other
// than `expected` ("<field>.width: expected 128, got 64"), DTYPE_UNSPECIFIED
// ("<field>.dtype: must be set"), unknown dtype or compression values, a
// byte count other than width*height*channels*sizeof(dtype) ("<field>.data:
// expected N bytes, got M"), a bad zstd frame ("<field>.data: zstd ..."; a
// frame whose declared content size is wrong is rejected without
// decompressing, one without a content size is decompressed into at most the
// expected size), NaN or Inf ("<field>.data: NaN at pixel (x, y) channel c").
// Thread-safety: pure function.
absl::StatusOr<ImageBuffer> DecodeImage(const v1::Image& image, std::string_view field,
                                        const ImageShape& expected);

// Same checks and errors as DecodeImage, always uint8 (float values
// quantised as round-half-even(x * 255) after clamping, like
// session::BasecolorBuffer), for the keyframes sessions keep.
// Thread-safety: pure function.
absl::StatusOr<ImageBuffer> DecodeImageBytes(const v1::Image& image, std::string_view field,
                                             const ImageShape& expected);

// Encodes a rendered RGB frame (3 channels, HWC) into `out` (overwritten;
// not owned): a uint8 `image` for OutputDType::kUint8, a float32 one ([0, 1],
// used as it is) for kFloat16 / kFloat32. float16 is IEEE binary16 rounded
// to nearest even, little endian. kZstd writes one zstd frame with its
// content size set.
// INVALID_ARGUMENT if the image is empty, has other than 3 channels or the
// wrong element type for `dtype` (out is then unchanged); INTERNAL on a zstd
// failure. Thread-safety: pure function.
absl::Status EncodeImage(const ImageBuffer& image, session::OutputDType dtype,
                         session::OutputCompression compression, v1::Image* out);

// IEEE 754 binary16 <-> binary32 (exposed for tests and for callers that
// convert in bulk). FloatToHalfBits rounds to nearest even; overflow gives
// +-Inf and NaN stays NaN. HalfBitsToFloat is exact.
uint16_t FloatToHalfBits(float value);
float HalfBitsToFloat(uint16_t bits);

}  // namespace fd::server

#endif  // FD_SERVER_IMAGE_CODEC_H_

// Image files: PNG (libpng) read/write, JPEG (libjpeg) read, OpenEXR read/write
// with one image per file or several named layers in one file.
//
// Started from tools/scenegen/image_io (same PNG and EXR writers, so equal
// images still give byte-identical files: no timestamps, fixed zlib level).
// All functions are thread-safe (no shared state) and never throw.
//
// Status codes: NOT_FOUND when a file to read does not exist; DATA_LOSS when
// it is not a valid file of its format or lacks the channels asked for;
// INVALID_ARGUMENT for an image that cannot be written (bad shape) or an
// unknown file extension; INTERNAL when the library fails to write. A file
// whose header claims more than kMaxReadSide pixels per side or kMaxReadPixels
// in all is DATA_LOSS before anything is allocated for it (the readers take
// files from elsewhere, e.g. a studio's dataset); EXR headers are validated
// by OpenEXRCore (strict header checks) before OpenEXR's C++ reader opens them.
#ifndef FD_CLIENT_SDK_IMAGE_IO_H_
#define FD_CLIENT_SDK_IMAGE_IO_H_

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "client_sdk/image.h"

namespace fd::client {

// Bounds on the images read: 16K per side, 64 Mpixel in all (768 MiB as
// float RGB; far above any G-buffer frame a client streams).
inline constexpr int64_t kMaxReadSide = 16384;
inline constexpr int64_t kMaxReadPixels = int64_t{8192} * 8192;

// ---------------------------------------------------------------- PNG / JPEG

// Writes an 8-bit gray (1 channel), RGB (3) or RGBA (4) PNG. The file carries
// no timestamp, so equal images give byte-identical files.
absl::Status WritePng(const std::string& path, const Image8& image);

// Reads a PNG as 8-bit, keeping gray as 1 channel and colour as 3 channels
// (alpha dropped, not composited; palettes expanded). 16-bit files are
// rescaled to 8 bits (round(v / 257)) without any gamma conversion (16-bit
// files with alpha are composited onto black by libpng).
absl::StatusOr<Image8> ReadPng(const std::string& path);

// Reads a baseline or progressive JPEG: gray as 1 channel, colour (YCbCr or
// RGB) as 3. CMYK files are DATA_LOSS.
absl::StatusOr<Image8> ReadJpeg(const std::string& path);

// ---------------------------------------------------------------- OpenEXR

// Writes a scanline EXR with ZIP compression: channel "Y" for one channel,
// "R","G","B" for three; FLOAT pixels for ImageF, HALF for ImageF16.
absl::Status WriteExr(const std::string& path, const ImageF& image);
absl::Status WriteExr(const std::string& path, const ImageF16& image);

// Reads a single-image EXR as float. Accepted channel sets (first match):
// R,G,B (an A is ignored) -> 3 channels; X,Y,Z -> 3; Y -> 1; any single
// channel (e.g. Z or V) -> 1. When the file has no unlayered channels but
// exactly one layer, that layer is read (e.g. "Depth.Y" alone).
absl::StatusOr<ImageF> ReadExr(const std::string& path);

// Layer names of an EXR whose channels are named "<layer>.<channel>" (the
// OpenEXR layer convention, e.g. "BaseColor.R", "Normals.X", "Depth.Y").
// Unlayered channels ("R", "G", "B") form the layer "" when present.
absl::StatusOr<std::vector<std::string>> ListExrLayers(const std::string& path);

// Reads one layer of a multi-layer EXR with the channel rules of ReadExr
// applied to the layer's channels. NOT_FOUND (naming the layers present)
// when the layer does not exist.
absl::StatusOr<ImageF> ReadExrLayer(const std::string& path, const std::string& layer);

// Writes several equally sized images as layers of one EXR: 3-channel images
// as "<name>.R/G/B", 1-channel images as "<name>.Y" (FLOAT, ZIP).
struct ExrLayer {
  std::string name;
  const ImageF* image = nullptr;
};
absl::Status WriteLayeredExr(const std::string& path, const std::vector<ExrLayer>& layers);

// ---------------------------------------------------------------- any format

// Size and channel count from the file header alone (no pixel decoding), for
// validating a dataset quickly. For EXR, channels follows ReadExr's rules.
struct ImageFileInfo {
  int width = 0;
  int height = 0;
  int channels = 0;
};
absl::StatusOr<ImageFileInfo> ReadImageInfo(const std::string& path);
// The same for one layer of a multi-layer EXR (NOT_FOUND without it).
absl::StatusOr<ImageFileInfo> ReadExrLayerInfo(const std::string& path, const std::string& layer);

// Reads by extension (case-insensitive): .png -> Image8, .jpg/.jpeg ->
// Image8, .exr -> ImageF. INVALID_ARGUMENT for another extension.
absl::StatusOr<AnyImage> ReadImage(const std::string& path);

// Writes by extension: .png (converted to uint8 if needed) or .exr (uint8 and
// float32 as FLOAT, float16 as HALF).
absl::Status WriteImage(const std::string& path, const AnyImage& image);

}  // namespace fd::client

#endif  // FD_CLIENT_SDK_IMAGE_IO_H_

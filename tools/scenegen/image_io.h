// Image containers and file I/O: 8-bit PNG (libpng) and float EXR (OpenEXR).
//
// Kept free of scene-generator types so it can move to a shared place (the
// client's dataset reader needs the same PNG reading). All functions are
// thread-safe (no shared state) and never throw.
#ifndef FD_TOOLS_SCENEGEN_IMAGE_IO_H_
#define FD_TOOLS_SCENEGEN_IMAGE_IO_H_

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace fd::scenegen {

// Interleaved 8-bit image, rows top to bottom; channels is 1 (gray) or 3 (RGB).
struct Image8 {
  int width = 0;
  int height = 0;
  int channels = 0;
  std::vector<uint8_t> pixels;  // size width * height * channels

  Image8() = default;
  Image8(int w, int h, int c) : width(w), height(h), channels(c), pixels(size_t(w) * h * c, 0) {}
  uint8_t& at(int x, int y, int c) { return pixels[(size_t(y) * width + x) * channels + c]; }
  uint8_t at(int x, int y, int c) const { return pixels[(size_t(y) * width + x) * channels + c]; }
};

// Interleaved float image, rows top to bottom; channels is 1 or 3.
struct ImageF {
  int width = 0;
  int height = 0;
  int channels = 0;
  std::vector<float> pixels;  // size width * height * channels

  ImageF() = default;
  ImageF(int w, int h, int c) : width(w), height(h), channels(c), pixels(size_t(w) * h * c, 0.0f) {}
  float& at(int x, int y, int c) { return pixels[(size_t(y) * width + x) * channels + c]; }
  float at(int x, int y, int c) const { return pixels[(size_t(y) * width + x) * channels + c]; }
};

// Writes an 8-bit gray (1 channel) or RGB (3 channel) PNG. The file carries no
// timestamp, so equal images give byte-identical files.
// INVALID_ARGUMENT for a bad image shape, INTERNAL when libpng fails to write.
absl::Status WritePng(const std::string& path, const Image8& image);

// Reads a PNG as 8-bit, keeping gray as 1 channel and colour as 3 channels
// (an alpha channel is dropped, a palette expanded).
// NOT_FOUND when the file is missing, DATA_LOSS when it is not a valid PNG.
absl::StatusOr<Image8> ReadPng(const std::string& path);

// Writes a scanline float32 EXR with ZIP compression: channel "Y" for one
// channel, "R", "G", "B" for three. INVALID_ARGUMENT for a bad shape,
// INTERNAL when OpenEXR fails.
absl::Status WriteExr(const std::string& path, const ImageF& image);

// Reads an EXR written by WriteExr (channels "Y" or "R","G","B") as float.
// NOT_FOUND when missing, DATA_LOSS when unreadable or the channels differ.
absl::StatusOr<ImageF> ReadExr(const std::string& path);

}  // namespace fd::scenegen

#endif  // FD_TOOLS_SCENEGEN_IMAGE_IO_H_

// Helpers shared by the client SDK tests: scratch folders and small
// deterministic images.
#ifndef FD_TESTS_CLIENT_SDK_TEST_UTIL_H_
#define FD_TESTS_CLIENT_SDK_TEST_UTIL_H_

#include <unistd.h>

#include <atomic>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <string>

#include "client_sdk/image.h"

// jpeglib.h needs <cstdio> (FILE, size_t) included before it.
// clang-format off
#include <jpeglib.h>
// clang-format on

namespace fd::client::testing {

// A fresh, empty folder removed when the object goes out of scope.
class ScratchDir {
 public:
  ScratchDir() {
    static std::atomic<int> counter{0};
    path_ = std::filesystem::temp_directory_path() /
            ("fd_client_test_" + std::to_string(::getpid()) + "_" + std::to_string(counter++));
    std::filesystem::remove_all(path_);
    std::filesystem::create_directories(path_);
  }
  ~ScratchDir() {
    std::error_code ec;
    std::filesystem::remove_all(path_, ec);
  }
  ScratchDir(const ScratchDir&) = delete;
  ScratchDir& operator=(const ScratchDir&) = delete;

  const std::filesystem::path& path() const { return path_; }
  std::string operator/(const std::string& relative) const { return (path_ / relative).string(); }

 private:
  std::filesystem::path path_;
};

// A deterministic pattern: every pixel/channel differs, seeded by `seed`.
inline Image8 Pattern8(int width, int height, int channels, int seed) {
  Image8 image(width, height, channels);
  uint32_t state = 2654435761u * static_cast<uint32_t>(seed + 1);
  for (uint8_t& v : image.pixels) {
    state = state * 1664525u + 1013904223u;
    v = static_cast<uint8_t>(state >> 24);
  }
  return image;
}

inline ImageF PatternF(int width, int height, int channels, int seed) {
  return ToFloat(ImageView::Of(Pattern8(width, height, channels, seed)));
}

// Writes a JPEG with libjpeg at quality 100 (gray or RGB), for the readers.
inline void WriteJpeg(const std::string& path, const Image8& image) {
  jpeg_compress_struct info;
  jpeg_error_mgr error;
  info.err = jpeg_std_error(&error);
  jpeg_create_compress(&info);
  std::FILE* file = std::fopen(path.c_str(), "wb");
  if (file == nullptr) return;
  jpeg_stdio_dest(&info, file);
  info.image_width = image.width;
  info.image_height = image.height;
  info.input_components = image.channels;
  info.in_color_space = image.channels == 1 ? JCS_GRAYSCALE : JCS_RGB;
  jpeg_set_defaults(&info);
  jpeg_set_quality(&info, 100, TRUE);
  jpeg_start_compress(&info, TRUE);
  while (info.next_scanline < info.image_height) {
    JSAMPROW row = const_cast<uint8_t*>(image.pixels.data()) +
                   size_t(info.next_scanline) * image.width * image.channels;
    jpeg_write_scanlines(&info, &row, 1);
  }
  jpeg_finish_compress(&info);
  jpeg_destroy_compress(&info);
  std::fclose(file);
}

}  // namespace fd::client::testing

#endif  // FD_TESTS_CLIENT_SDK_TEST_UTIL_H_

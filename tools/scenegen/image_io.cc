#include "tools/scenegen/image_io.h"

#include <OpenEXR/ImfChannelList.h>
#include <OpenEXR/ImfFrameBuffer.h>
#include <OpenEXR/ImfHeader.h>
#include <OpenEXR/ImfInputFile.h>
#include <OpenEXR/ImfOutputFile.h>
#include <png.h>

#include <cerrno>
#include <csetjmp>
#include <cstdio>
#include <cstring>
#include <exception>
#include <filesystem>
#include <memory>

#include "absl/strings/str_cat.h"

namespace fd::scenegen {
namespace {

// libpng reports errors by calling this and expecting a longjmp; the message
// is kept so the caller can return it in a Status.
struct PngErrorState {
  char message[256] = {0};
};

void PngErrorFn(png_structp png, png_const_charp message) {
  auto* state = static_cast<PngErrorState*>(png_get_error_ptr(png));
  std::snprintf(state->message, sizeof(state->message), "%s", message);
  png_longjmp(png, 1);
}

void PngWarningFn(png_structp, png_const_charp) {}

// The setjmp/longjmp region: only trivially destructible locals live here, so
// a libpng error cannot skip a C++ destructor. Returns true on success.
bool WritePngRows(std::FILE* file, int width, int height, int color_type, png_bytep* rows,
                  PngErrorState* error) {
  png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, error, PngErrorFn, PngWarningFn);
  if (png == nullptr) {
    std::snprintf(error->message, sizeof(error->message), "png_create_write_struct failed");
    return false;
  }
  png_infop info = png_create_info_struct(png);
  if (info == nullptr) {
    png_destroy_write_struct(&png, nullptr);
    std::snprintf(error->message, sizeof(error->message), "png_create_info_struct failed");
    return false;
  }
  if (setjmp(png_jmpbuf(png))) {
    png_destroy_write_struct(&png, &info);
    return false;
  }
  png_init_io(png, file);
  // A fast zlib level: the buffers are large and smooth, level 6 gains little.
  png_set_compression_level(png, 3);
  png_set_IHDR(png, info, static_cast<png_uint_32>(width), static_cast<png_uint_32>(height), 8,
               color_type, PNG_INTERLACE_NONE, PNG_COMPRESSION_TYPE_DEFAULT,
               PNG_FILTER_TYPE_DEFAULT);
  png_write_info(png, info);
  png_write_image(png, rows);
  png_write_end(png, nullptr);
  png_destroy_write_struct(&png, &info);
  return true;
}

absl::Status CheckShape(int width, int height, int channels, size_t size) {
  if (width <= 0 || height <= 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("image size must be positive, got ", width, "x", height));
  }
  if (channels != 1 && channels != 3) {
    return absl::InvalidArgumentError(
        absl::StrCat("image channels must be 1 or 3, got ", channels));
  }
  if (size != size_t(width) * height * channels) {
    return absl::InvalidArgumentError(absl::StrCat(
        "image pixel buffer has ", size, " values, expected ", width, "*", height, "*", channels));
  }
  return absl::OkStatus();
}

}  // namespace

absl::Status WritePng(const std::string& path, const Image8& image) {
  if (absl::Status s = CheckShape(image.width, image.height, image.channels, image.pixels.size());
      !s.ok()) {
    return s;
  }
  std::vector<png_bytep> rows(image.height);
  for (int y = 0; y < image.height; ++y) {
    rows[y] = const_cast<png_bytep>(image.pixels.data() + size_t(y) * image.width * image.channels);
  }
  std::unique_ptr<std::FILE, int (*)(std::FILE*)> file(std::fopen(path.c_str(), "wb"),
                                                       &std::fclose);
  if (file == nullptr) {
    return absl::InternalError(
        absl::StrCat("cannot open ", path, " for writing: ", std::strerror(errno)));
  }
  PngErrorState error;
  const int color_type = image.channels == 1 ? PNG_COLOR_TYPE_GRAY : PNG_COLOR_TYPE_RGB;
  if (!WritePngRows(file.get(), image.width, image.height, color_type, rows.data(), &error)) {
    return absl::InternalError(absl::StrCat("libpng failed writing ", path, ": ", error.message));
  }
  if (std::fclose(file.release()) != 0) {
    return absl::InternalError(absl::StrCat("cannot close ", path, ": ", std::strerror(errno)));
  }
  return absl::OkStatus();
}

absl::StatusOr<Image8> ReadPng(const std::string& path) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) {
    return absl::NotFoundError(absl::StrCat("no such PNG file: ", path));
  }
  // libpng's simplified API handles its errors internally (no setjmp here).
  png_image png;
  std::memset(&png, 0, sizeof(png));
  png.version = PNG_IMAGE_VERSION;
  if (png_image_begin_read_from_file(&png, path.c_str()) == 0) {
    return absl::DataLossError(absl::StrCat("cannot read PNG ", path, ": ", png.message));
  }
  const bool color = (png.format & PNG_FORMAT_FLAG_COLOR) != 0;
  png.format = color ? PNG_FORMAT_RGB : PNG_FORMAT_GRAY;
  Image8 image(static_cast<int>(png.width), static_cast<int>(png.height), color ? 3 : 1);
  if (png_image_finish_read(&png, nullptr, image.pixels.data(), 0, nullptr) == 0) {
    png_image_free(&png);
    return absl::DataLossError(absl::StrCat("cannot decode PNG ", path, ": ", png.message));
  }
  return image;
}

absl::Status WriteExr(const std::string& path, const ImageF& image) {
  if (absl::Status s = CheckShape(image.width, image.height, image.channels, image.pixels.size());
      !s.ok()) {
    return s;
  }
  static constexpr const char* kRgb[] = {"R", "G", "B"};
  try {
    Imf::Header header(image.width, image.height);
    header.compression() = Imf::ZIP_COMPRESSION;
    Imf::FrameBuffer frame_buffer;
    const size_t x_stride = sizeof(float) * image.channels;
    const size_t y_stride = x_stride * image.width;
    for (int c = 0; c < image.channels; ++c) {
      const char* name = image.channels == 1 ? "Y" : kRgb[c];
      header.channels().insert(name, Imf::Channel(Imf::FLOAT));
      char* base = reinterpret_cast<char*>(const_cast<float*>(image.pixels.data() + c));
      frame_buffer.insert(name, Imf::Slice(Imf::FLOAT, base, x_stride, y_stride));
    }
    Imf::OutputFile file(path.c_str(), header);
    file.setFrameBuffer(frame_buffer);
    file.writePixels(image.height);
  } catch (const std::exception& e) {
    return absl::InternalError(absl::StrCat("OpenEXR failed writing ", path, ": ", e.what()));
  }
  return absl::OkStatus();
}

absl::StatusOr<ImageF> ReadExr(const std::string& path) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) {
    return absl::NotFoundError(absl::StrCat("no such EXR file: ", path));
  }
  try {
    Imf::InputFile file(path.c_str());
    const Imath::Box2i window = file.header().dataWindow();
    const int width = window.max.x - window.min.x + 1;
    const int height = window.max.y - window.min.y + 1;
    const Imf::ChannelList& channels = file.header().channels();
    std::vector<std::string> names;
    if (channels.findChannel("Y") != nullptr) {
      names = {"Y"};
    } else if (channels.findChannel("R") && channels.findChannel("G") &&
               channels.findChannel("B")) {
      names = {"R", "G", "B"};
    } else {
      return absl::DataLossError(absl::StrCat("EXR ", path, " has neither Y nor R,G,B channels"));
    }
    ImageF image(width, height, static_cast<int>(names.size()));
    Imf::FrameBuffer frame_buffer;
    const size_t x_stride = sizeof(float) * image.channels;
    const size_t y_stride = x_stride * width;
    for (int c = 0; c < image.channels; ++c) {
      // OpenEXR addresses pixels by absolute data-window coordinates.
      char* base = reinterpret_cast<char*>(image.pixels.data() + c) - window.min.x * x_stride -
                   window.min.y * y_stride;
      frame_buffer.insert(names[c], Imf::Slice(Imf::FLOAT, base, x_stride, y_stride));
    }
    file.setFrameBuffer(frame_buffer);
    file.readPixels(window.min.y, window.max.y);
    return image;
  } catch (const std::exception& e) {
    return absl::DataLossError(absl::StrCat("cannot read EXR ", path, ": ", e.what()));
  }
}

}  // namespace fd::scenegen

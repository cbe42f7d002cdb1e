#include "client_sdk/image_io.h"

#include <OpenEXR/ImfChannelList.h>
#include <OpenEXR/ImfFrameBuffer.h>
#include <OpenEXR/ImfHeader.h>
#include <OpenEXR/ImfInputFile.h>
#include <OpenEXR/ImfOutputFile.h>
#include <OpenEXR/openexr.h>
#include <png.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <csetjmp>
#include <cstdio>
#include <cstring>
#include <exception>
#include <filesystem>
#include <memory>
#include <set>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

// jpeglib.h needs <cstdio> (FILE, size_t) included before it.
// clang-format off
#include <jpeglib.h>
// clang-format on

namespace fd::client {
namespace {

using FilePtr = std::unique_ptr<std::FILE, int (*)(std::FILE*)>;

absl::Status CheckReadable(const std::string& path, const char* kind) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) {
    return absl::NotFoundError(absl::StrCat("no such ", kind, " file: ", path));
  }
  return absl::OkStatus();
}

// Untrusted files (a dataset from elsewhere) choose their own sizes: a header
// may claim 1,000,000 x 1,000,000 pixels in a few bytes. Nothing is
// allocated for an image larger than these bounds (found by
// tests/fuzz/fuzz_image_file.cc).
absl::Status CheckImageSize(const char* kind, const std::string& path, int64_t width,
                            int64_t height) {
  if (width < 1 || height < 1 || width > kMaxReadSide || height > kMaxReadSide ||
      width * height > kMaxReadPixels) {
    return absl::DataLossError(absl::StrCat("cannot read ", kind, " ", path, ": ", width, " x ",
                                            height, " pixels is outside the sizes read (1 to ",
                                            kMaxReadSide, " per side, at most ", kMaxReadPixels,
                                            " pixels)"));
  }
  return absl::OkStatus();
}

absl::Status CheckShape(int width, int height, int channels, size_t size,
                        std::initializer_list<int> allowed_channels) {
  if (width <= 0 || height <= 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("image size must be positive, got ", width, "x", height));
  }
  if (std::find(allowed_channels.begin(), allowed_channels.end(), channels) ==
      allowed_channels.end()) {
    return absl::InvalidArgumentError(absl::StrCat("image channels must be one of ",
                                                   absl::StrJoin(allowed_channels, ", "), ", got ",
                                                   channels));
  }
  if (size != size_t(width) * height * channels) {
    return absl::InvalidArgumentError(absl::StrCat(
        "image pixel buffer has ", size, " values, expected ", width, "*", height, "*", channels));
  }
  return absl::OkStatus();
}

std::string LowerExtension(const std::string& path) {
  return absl::AsciiStrToLower(std::filesystem::path(path).extension().string());
}

// ------------------------------------------------------------------- PNG

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

// Opens a PNG with libpng's simplified API (which handles its own errors).
absl::Status BeginPng(const std::string& path, png_image* png) {
  if (absl::Status s = CheckReadable(path, "PNG"); !s.ok()) return s;
  std::memset(png, 0, sizeof(*png));
  png->version = PNG_IMAGE_VERSION;
  if (png_image_begin_read_from_file(png, path.c_str()) == 0) {
    return absl::DataLossError(absl::StrCat("cannot read PNG ", path, ": ", png->message));
  }
  if (absl::Status s = CheckImageSize("PNG", path, png->width, png->height); !s.ok()) {
    png_image_free(png);
    return s;
  }
  return absl::OkStatus();
}

// ------------------------------------------------------------------- JPEG

struct JpegErrorManager {
  jpeg_error_mgr base;
  std::jmp_buf jump;
  char message[JMSG_LENGTH_MAX] = {0};
};

void JpegErrorExit(j_common_ptr info) {
  auto* manager = reinterpret_cast<JpegErrorManager*>(info->err);
  (*info->err->format_message)(info, manager->message);
  std::longjmp(manager->jump, 1);
}

// The setjmp region for libjpeg: only trivially destructible locals; the
// output buffer is pre-sized by the caller after the header pass. When
// `pixels` is null only the header is read. Returns false on error.
bool DecodeJpeg(std::FILE* file, JpegErrorManager* error, int* width, int* height, int* channels,
                std::vector<uint8_t>* pixels) {
  jpeg_decompress_struct info;
  info.err = jpeg_std_error(&error->base);
  error->base.error_exit = JpegErrorExit;
  if (setjmp(error->jump)) {
    jpeg_destroy_decompress(&info);
    return false;
  }
  jpeg_create_decompress(&info);
  jpeg_stdio_src(&info, file);
  jpeg_read_header(&info, TRUE);
  if (info.jpeg_color_space == JCS_CMYK || info.jpeg_color_space == JCS_YCCK) {
    std::snprintf(error->message, sizeof(error->message), "CMYK JPEGs are not supported");
    jpeg_destroy_decompress(&info);
    return false;
  }
  if (absl::Status s = CheckImageSize("JPEG", "", info.image_width, info.image_height); !s.ok()) {
    std::snprintf(error->message, sizeof(error->message),
                  "%u x %u pixels is outside the sizes read", info.image_width, info.image_height);
    jpeg_destroy_decompress(&info);
    return false;
  }
  const bool gray = info.num_components == 1;
  info.out_color_space = gray ? JCS_GRAYSCALE : JCS_RGB;
  *width = static_cast<int>(info.image_width);
  *height = static_cast<int>(info.image_height);
  *channels = gray ? 1 : 3;
  if (pixels == nullptr) {
    jpeg_destroy_decompress(&info);
    return true;
  }
  pixels->resize(size_t(*width) * *height * *channels);
  jpeg_start_decompress(&info);
  const size_t row_bytes = size_t(*width) * *channels;
  while (info.output_scanline < info.output_height) {
    JSAMPROW row = pixels->data() + size_t(info.output_scanline) * row_bytes;
    jpeg_read_scanlines(&info, &row, 1);
  }
  jpeg_finish_decompress(&info);
  jpeg_destroy_decompress(&info);
  return true;
}

absl::StatusOr<Image8> ReadJpegImpl(const std::string& path, bool header_only) {
  if (absl::Status s = CheckReadable(path, "JPEG"); !s.ok()) return s;
  FilePtr file(std::fopen(path.c_str(), "rb"), &std::fclose);
  if (file == nullptr) {
    return absl::DataLossError(absl::StrCat("cannot open ", path, ": ", std::strerror(errno)));
  }
  JpegErrorManager error;
  Image8 image;
  if (!DecodeJpeg(file.get(), &error, &image.width, &image.height, &image.channels,
                  header_only ? nullptr : &image.pixels)) {
    return absl::DataLossError(absl::StrCat("cannot read JPEG ", path, ": ", error.message));
  }
  return image;
}

// ------------------------------------------------------------------- EXR

// Full channel names to read for `layer` ("" = unlayered channels), in
// output channel order; see ReadExr for the rules.
absl::StatusOr<std::vector<std::string>> ResolveExrChannels(const Imf::ChannelList& list,
                                                            const std::string& layer,
                                                            const std::string& path) {
  std::set<std::string> suffixes;
  for (auto it = list.begin(); it != list.end(); ++it) {
    const std::string name = it.name();
    const size_t dot = name.rfind('.');
    const std::string channel_layer = dot == std::string::npos ? "" : name.substr(0, dot);
    if (channel_layer == layer)
      suffixes.insert(dot == std::string::npos ? name : name.substr(dot + 1));
  }
  const std::string prefix = layer.empty() ? "" : layer + ".";
  auto has = [&](const char* s) { return suffixes.count(s) > 0; };
  std::vector<std::string> picked;
  if (has("R") && has("G") && has("B")) {
    picked = {"R", "G", "B"};
  } else if (has("X") && has("Y") && has("Z")) {
    picked = {"X", "Y", "Z"};
  } else if (has("Y")) {
    picked = {"Y"};
  } else if (suffixes.size() == 1) {
    picked = {*suffixes.begin()};
  } else {
    std::string what = layer.empty() ? "unlayered channels" : absl::StrCat("layer '", layer, "'");
    return absl::DataLossError(absl::StrCat("EXR ", path, ": ", what, " [",
                                            absl::StrJoin(suffixes, ","),
                                            "] are none of R,G,B / X,Y,Z / Y / a single channel"));
  }
  for (std::string& name : picked) name = prefix + name;
  return picked;
}

std::vector<std::string> LayersOf(const Imf::ChannelList& list) {
  std::set<std::string> layers;
  list.layers(layers);
  std::vector<std::string> out;
  for (auto it = list.begin(); it != list.end(); ++it) {
    if (std::strchr(it.name(), '.') == nullptr) {
      out.push_back("");
      break;
    }
  }
  out.insert(out.end(), layers.begin(), layers.end());
  return out;
}

// The layer ReadExr reads: unlayered channels, else the only layer.
absl::StatusOr<std::string> DefaultExrLayer(const Imf::ChannelList& list, const std::string& path) {
  const std::vector<std::string> layers = LayersOf(list);
  if (!layers.empty() && layers.front().empty()) return std::string();
  if (layers.size() == 1) return layers.front();
  return absl::DataLossError(absl::StrCat("EXR ", path, " has no unlayered channels but ",
                                          layers.size(), " layers (", absl::StrJoin(layers, ", "),
                                          "); read one layer"));
}

// OpenEXR's C++ reader (3.1) allocates what an attribute's size field says
// (up to 2 GiB) before reading the value, and reads fixed-size attributes
// whatever size the file declares, so a 300-byte file can ask for gigabytes
// (found by tests/fuzz/fuzz_image_file.cc). OpenEXRCore, the hardened C
// reader of the same release, parses every header first: sizes that do not
// match the type or run past the file, and data or tile windows above
// kMaxReadSide, fail there with its message, before the C++ reader runs.
void CaptureExrCoreError(exr_const_context_t context, exr_result_t code, const char* message) {
  void* user_data = nullptr;
  if (exr_get_user_data(context, &user_data) == EXR_ERR_SUCCESS && user_data != nullptr) {
    *static_cast<std::string*>(user_data) = message != nullptr ? message : "";
  }
}

absl::Status CheckExrHeaders(const std::string& path) {
  std::string message;
  exr_context_initializer_t init = EXR_DEFAULT_CONTEXT_INITIALIZER;
  init.error_handler_fn = &CaptureExrCoreError;
  init.user_data = &message;
  init.max_image_width = init.max_image_height = static_cast<int>(kMaxReadSide);
  init.max_tile_width = init.max_tile_height = static_cast<int>(kMaxReadSide);
  init.flags = EXR_CONTEXT_FLAG_STRICT_HEADER;
  exr_context_t context = nullptr;
  const exr_result_t result = exr_start_read(&context, path.c_str(), &init);
  if (context != nullptr) exr_finish(&context);
  if (result != EXR_ERR_SUCCESS) {
    if (message.empty()) message = exr_get_default_error_message(result);
    return absl::DataLossError(absl::StrCat("cannot read EXR ", path, ": ", message));
  }
  return absl::OkStatus();
}

// An EXR opened for reading, its header and data window checked (throws what
// OpenEXR throws; the callers turn it into DATA_LOSS).
absl::StatusOr<std::unique_ptr<Imf::InputFile>> OpenExr(const std::string& path) {
  if (absl::Status s = CheckReadable(path, "EXR"); !s.ok()) return s;
  if (absl::Status s = CheckExrHeaders(path); !s.ok()) return s;
  auto file = std::make_unique<Imf::InputFile>(path.c_str());
  const Imath::Box2i window = file->header().dataWindow();
  if (absl::Status s = CheckImageSize("EXR", path, int64_t{window.max.x} - window.min.x + 1,
                                      int64_t{window.max.y} - window.min.y + 1);
      !s.ok()) {
    return s;
  }
  return file;
}

absl::StatusOr<ImageF> ReadExrChannels(Imf::InputFile& file,
                                       const std::vector<std::string>& names) {
  const Imath::Box2i window = file.header().dataWindow();
  const int width = window.max.x - window.min.x + 1;
  const int height = window.max.y - window.min.y + 1;
  ImageF image(width, height, static_cast<int>(names.size()));
  Imf::FrameBuffer frame_buffer;
  const size_t x_stride = sizeof(float) * image.channels;
  const size_t y_stride = x_stride * width;
  for (int c = 0; c < image.channels; ++c) {
    // OpenEXR addresses pixels by absolute data-window coordinates; Make
    // shifts the base by the window's origin in integer arithmetic (a
    // pointer moved outside the buffer would be undefined behaviour).
    frame_buffer.insert(names[c], Imf::Slice::Make(Imf::FLOAT, image.pixels.data() + c, window,
                                                   x_stride, y_stride));
  }
  file.setFrameBuffer(frame_buffer);
  file.readPixels(window.min.y, window.max.y);
  return image;
}

// One writer for every EXR this file produces: `channels[i]` is the full
// channel name of element `offset[i]` in image `sources[i]`.
struct ExrChannelSource {
  std::string name;
  const char* base = nullptr;  // first element of this channel
  Imf::PixelType type = Imf::FLOAT;
  size_t x_stride = 0;
  size_t y_stride = 0;
};

absl::Status WriteExrChannels(const std::string& path, int width, int height,
                              const std::vector<ExrChannelSource>& sources) {
  try {
    Imf::Header header(width, height);
    header.compression() = Imf::ZIP_COMPRESSION;
    Imf::FrameBuffer frame_buffer;
    for (const ExrChannelSource& source : sources) {
      header.channels().insert(source.name, Imf::Channel(source.type));
      frame_buffer.insert(source.name, Imf::Slice(source.type, const_cast<char*>(source.base),
                                                  source.x_stride, source.y_stride));
    }
    Imf::OutputFile file(path.c_str(), header);
    file.setFrameBuffer(frame_buffer);
    file.writePixels(height);
  } catch (const std::exception& e) {
    return absl::InternalError(absl::StrCat("OpenEXR failed writing ", path, ": ", e.what()));
  }
  return absl::OkStatus();
}

template <typename T>
absl::Status WriteSingleExr(const std::string& path, const ImageT<T>& image, Imf::PixelType type) {
  if (absl::Status s =
          CheckShape(image.width, image.height, image.channels, image.pixels.size(), {1, 3});
      !s.ok()) {
    return s;
  }
  static constexpr const char* kRgb[] = {"R", "G", "B"};
  std::vector<ExrChannelSource> sources;
  for (int c = 0; c < image.channels; ++c) {
    ExrChannelSource source;
    source.name = image.channels == 1 ? "Y" : kRgb[c];
    source.base = reinterpret_cast<const char*>(image.pixels.data() + c);
    source.type = type;
    source.x_stride = sizeof(T) * image.channels;
    source.y_stride = source.x_stride * image.width;
    sources.push_back(source);
  }
  return WriteExrChannels(path, image.width, image.height, sources);
}

}  // namespace

absl::Status WritePng(const std::string& path, const Image8& image) {
  if (absl::Status s =
          CheckShape(image.width, image.height, image.channels, image.pixels.size(), {1, 3, 4});
      !s.ok()) {
    return s;
  }
  std::vector<png_bytep> rows(image.height);
  for (int y = 0; y < image.height; ++y) {
    rows[y] = const_cast<png_bytep>(image.pixels.data() + size_t(y) * image.width * image.channels);
  }
  FilePtr file(std::fopen(path.c_str(), "wb"), &std::fclose);
  if (file == nullptr) {
    return absl::InternalError(
        absl::StrCat("cannot open ", path, " for writing: ", std::strerror(errno)));
  }
  PngErrorState error;
  const int color_type = image.channels == 1   ? PNG_COLOR_TYPE_GRAY
                         : image.channels == 3 ? PNG_COLOR_TYPE_RGB
                                               : PNG_COLOR_TYPE_RGB_ALPHA;
  if (!WritePngRows(file.get(), image.width, image.height, color_type, rows.data(), &error)) {
    return absl::InternalError(absl::StrCat("libpng failed writing ", path, ": ", error.message));
  }
  if (std::fclose(file.release()) != 0) {
    return absl::InternalError(absl::StrCat("cannot close ", path, ": ", std::strerror(errno)));
  }
  return absl::OkStatus();
}

absl::StatusOr<Image8> ReadPng(const std::string& path) {
  png_image png;
  if (absl::Status s = BeginPng(path, &png); !s.ok()) return s;
  const bool color = (png.format & PNG_FORMAT_FLAG_COLOR) != 0;
  const int channels = color ? 3 : 1;
  const size_t count = size_t(png.width) * png.height * channels;
  Image8 image(static_cast<int>(png.width), static_cast<int>(png.height), channels);
  if ((png.format & PNG_FORMAT_FLAG_LINEAR) != 0) {
    // A 16-bit file: read the 16-bit values as stored (libpng treats 16-bit
    // data as linear, so asking for 8 bits would apply an sRGB encoding).
    png.format = color ? PNG_FORMAT_LINEAR_RGB : PNG_FORMAT_LINEAR_Y;
    std::vector<uint16_t> wide(count);
    if (png_image_finish_read(&png, nullptr, wide.data(), 0, nullptr) == 0) {
      png_image_free(&png);
      return absl::DataLossError(absl::StrCat("cannot decode PNG ", path, ": ", png.message));
    }
    for (size_t i = 0; i < count; ++i)
      image.pixels[i] = static_cast<uint8_t>((wide[i] + 128) / 257);
    return image;
  }
  if ((png.format & PNG_FORMAT_FLAG_ALPHA) != 0) {
    // Read with alpha and drop it: asking libpng for no alpha would
    // composite the colour onto black.
    png.format = color ? PNG_FORMAT_RGBA : PNG_FORMAT_GA;
    std::vector<uint8_t> with_alpha(size_t(png.width) * png.height * (channels + 1));
    if (png_image_finish_read(&png, nullptr, with_alpha.data(), 0, nullptr) == 0) {
      png_image_free(&png);
      return absl::DataLossError(absl::StrCat("cannot decode PNG ", path, ": ", png.message));
    }
    for (size_t p = 0; p < size_t(png.width) * png.height; ++p) {
      for (int c = 0; c < channels; ++c)
        image.pixels[p * channels + c] = with_alpha[p * (channels + 1) + c];
    }
    return image;
  }
  png.format = color ? PNG_FORMAT_RGB : PNG_FORMAT_GRAY;
  if (png_image_finish_read(&png, nullptr, image.pixels.data(), 0, nullptr) == 0) {
    png_image_free(&png);
    return absl::DataLossError(absl::StrCat("cannot decode PNG ", path, ": ", png.message));
  }
  return image;
}

absl::StatusOr<Image8> ReadJpeg(const std::string& path) { return ReadJpegImpl(path, false); }

absl::Status WriteExr(const std::string& path, const ImageF& image) {
  return WriteSingleExr(path, image, Imf::FLOAT);
}

absl::Status WriteExr(const std::string& path, const ImageF16& image) {
  return WriteSingleExr(path, image, Imf::HALF);
}

absl::StatusOr<ImageF> ReadExr(const std::string& path) {
  try {
    absl::StatusOr<std::unique_ptr<Imf::InputFile>> opened = OpenExr(path);
    if (!opened.ok()) return opened.status();
    Imf::InputFile& file = **opened;
    absl::StatusOr<std::string> layer = DefaultExrLayer(file.header().channels(), path);
    if (!layer.ok()) return layer.status();
    absl::StatusOr<std::vector<std::string>> names =
        ResolveExrChannels(file.header().channels(), *layer, path);
    if (!names.ok()) return names.status();
    return ReadExrChannels(file, *names);
  } catch (const std::exception& e) {
    return absl::DataLossError(absl::StrCat("cannot read EXR ", path, ": ", e.what()));
  }
}

absl::StatusOr<std::vector<std::string>> ListExrLayers(const std::string& path) {
  try {
    absl::StatusOr<std::unique_ptr<Imf::InputFile>> opened = OpenExr(path);
    if (!opened.ok()) return opened.status();
    Imf::InputFile& file = **opened;
    return LayersOf(file.header().channels());
  } catch (const std::exception& e) {
    return absl::DataLossError(absl::StrCat("cannot read EXR ", path, ": ", e.what()));
  }
}

absl::StatusOr<ImageF> ReadExrLayer(const std::string& path, const std::string& layer) {
  try {
    absl::StatusOr<std::unique_ptr<Imf::InputFile>> opened = OpenExr(path);
    if (!opened.ok()) return opened.status();
    Imf::InputFile& file = **opened;
    const std::vector<std::string> layers = LayersOf(file.header().channels());
    if (std::find(layers.begin(), layers.end(), layer) == layers.end()) {
      return absl::NotFoundError(absl::StrCat("EXR ", path, " has no layer '", layer,
                                              "' (layers: ", absl::StrJoin(layers, ", "), ")"));
    }
    absl::StatusOr<std::vector<std::string>> names =
        ResolveExrChannels(file.header().channels(), layer, path);
    if (!names.ok()) return names.status();
    return ReadExrChannels(file, *names);
  } catch (const std::exception& e) {
    return absl::DataLossError(absl::StrCat("cannot read EXR ", path, ": ", e.what()));
  }
}

absl::Status WriteLayeredExr(const std::string& path, const std::vector<ExrLayer>& layers) {
  if (layers.empty() || layers.front().image == nullptr) {
    return absl::InvalidArgumentError("WriteLayeredExr: no layers");
  }
  const int width = layers.front().image->width;
  const int height = layers.front().image->height;
  std::vector<ExrChannelSource> sources;
  static constexpr const char* kRgb[] = {"R", "G", "B"};
  for (const ExrLayer& layer : layers) {
    const ImageF* image = layer.image;
    if (image == nullptr || layer.name.empty()) {
      return absl::InvalidArgumentError("WriteLayeredExr: a layer without a name or image");
    }
    if (absl::Status s =
            CheckShape(image->width, image->height, image->channels, image->pixels.size(), {1, 3});
        !s.ok()) {
      return absl::InvalidArgumentError(absl::StrCat("layer ", layer.name, ": ", s.message()));
    }
    if (image->width != width || image->height != height) {
      return absl::InvalidArgumentError(absl::StrCat("layer ", layer.name, " is ", image->width,
                                                     "x", image->height, ", the first layer is ",
                                                     width, "x", height));
    }
    for (int c = 0; c < image->channels; ++c) {
      ExrChannelSource source;
      source.name = absl::StrCat(layer.name, ".", image->channels == 1 ? "Y" : kRgb[c]);
      source.base = reinterpret_cast<const char*>(image->pixels.data() + c);
      source.x_stride = sizeof(float) * image->channels;
      source.y_stride = source.x_stride * width;
      sources.push_back(source);
    }
  }
  return WriteExrChannels(path, width, height, sources);
}

absl::StatusOr<ImageFileInfo> ReadExrLayerInfo(const std::string& path, const std::string& layer) {
  try {
    absl::StatusOr<std::unique_ptr<Imf::InputFile>> opened = OpenExr(path);
    if (!opened.ok()) return opened.status();
    Imf::InputFile& file = **opened;
    const std::vector<std::string> layers = LayersOf(file.header().channels());
    if (std::find(layers.begin(), layers.end(), layer) == layers.end()) {
      return absl::NotFoundError(absl::StrCat("EXR ", path, " has no layer '", layer,
                                              "' (layers: ", absl::StrJoin(layers, ", "), ")"));
    }
    absl::StatusOr<std::vector<std::string>> names =
        ResolveExrChannels(file.header().channels(), layer, path);
    if (!names.ok()) return names.status();
    const Imath::Box2i window = file.header().dataWindow();
    return ImageFileInfo{window.max.x - window.min.x + 1, window.max.y - window.min.y + 1,
                         static_cast<int>(names->size())};
  } catch (const std::exception& e) {
    return absl::DataLossError(absl::StrCat("cannot read EXR ", path, ": ", e.what()));
  }
}

absl::StatusOr<ImageFileInfo> ReadImageInfo(const std::string& path) {
  const std::string ext = LowerExtension(path);
  ImageFileInfo info;
  if (ext == ".png") {
    png_image png;
    if (absl::Status s = BeginPng(path, &png); !s.ok()) return s;
    info.width = static_cast<int>(png.width);
    info.height = static_cast<int>(png.height);
    info.channels = (png.format & PNG_FORMAT_FLAG_COLOR) != 0 ? 3 : 1;
    png_image_free(&png);
    return info;
  }
  if (ext == ".jpg" || ext == ".jpeg") {
    absl::StatusOr<Image8> header = ReadJpegImpl(path, /*header_only=*/true);
    if (!header.ok()) return header.status();
    return ImageFileInfo{header->width, header->height, header->channels};
  }
  if (ext == ".exr") {
    try {
      absl::StatusOr<std::unique_ptr<Imf::InputFile>> opened = OpenExr(path);
      if (!opened.ok()) return opened.status();
      Imf::InputFile& file = **opened;
      const Imath::Box2i window = file.header().dataWindow();
      info.width = window.max.x - window.min.x + 1;
      info.height = window.max.y - window.min.y + 1;
      absl::StatusOr<std::string> layer = DefaultExrLayer(file.header().channels(), path);
      if (!layer.ok()) return layer.status();
      absl::StatusOr<std::vector<std::string>> names =
          ResolveExrChannels(file.header().channels(), *layer, path);
      if (!names.ok()) return names.status();
      info.channels = static_cast<int>(names->size());
      return info;
    } catch (const std::exception& e) {
      return absl::DataLossError(absl::StrCat("cannot read EXR ", path, ": ", e.what()));
    }
  }
  return absl::InvalidArgumentError(absl::StrCat("unsupported image file extension '", ext, "': ",
                                                 path, " (expected .png, .jpg, .jpeg or .exr)"));
}

absl::StatusOr<AnyImage> ReadImage(const std::string& path) {
  const std::string ext = LowerExtension(path);
  if (ext == ".png") {
    absl::StatusOr<Image8> image = ReadPng(path);
    if (!image.ok()) return image.status();
    return AnyImage(std::move(*image));
  }
  if (ext == ".jpg" || ext == ".jpeg") {
    absl::StatusOr<Image8> image = ReadJpeg(path);
    if (!image.ok()) return image.status();
    return AnyImage(std::move(*image));
  }
  if (ext == ".exr") {
    absl::StatusOr<ImageF> image = ReadExr(path);
    if (!image.ok()) return image.status();
    return AnyImage(std::move(*image));
  }
  return absl::InvalidArgumentError(absl::StrCat("unsupported image file extension '", ext, "': ",
                                                 path, " (expected .png, .jpg, .jpeg or .exr)"));
}

absl::Status WriteImage(const std::string& path, const AnyImage& image) {
  const std::string ext = LowerExtension(path);
  if (ext == ".png") {
    if (const auto* u8 = std::get_if<Image8>(&image)) return WritePng(path, *u8);
    return WritePng(path, ToUint8(image));
  }
  if (ext == ".exr") {
    if (const auto* f16 = std::get_if<ImageF16>(&image)) return WriteExr(path, *f16);
    if (const auto* f32 = std::get_if<ImageF>(&image)) return WriteExr(path, *f32);
    return WriteExr(path, ToFloat(image));
  }
  return absl::InvalidArgumentError(
      absl::StrCat("cannot write '", ext, "' files: ", path, " (expected .png or .exr)"));
}

}  // namespace fd::client

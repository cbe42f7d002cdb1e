// Image containers shared by the SDK, the dataset reader and the CLI: owning
// interleaved images in uint8 / float16 / float32 and a non-owning ImageView
// over pixels somebody else owns (a game engine's readback buffer).
//
// Layout everywhere: row-major, interleaved (HWC), top row first; pixel (x, y),
// channel c is element ((y * width) + x) * channels + c, as on the wire
// (proto/framediffuser/v1/image.proto). No gRPC or protobuf here, so tools
// that only read and write images can use this without the SDK.
//
// Thread-safety: plain values; concurrent reads are safe, writes need the
// caller's synchronisation. Nothing here throws.
#ifndef FD_CLIENT_SDK_IMAGE_H_
#define FD_CLIENT_SDK_IMAGE_H_

#include <cstddef>
#include <cstdint>
#include <string_view>
#include <variant>
#include <vector>

namespace fd::client {

// Element type of an image (mirrors framediffuser.v1.DType).
enum class DType {
  kUint8,    // 0..255 maps linearly to [0, 1]
  kFloat16,  // IEEE 754 binary16
  kFloat32,  // IEEE 754 binary32
};

// Bytes per element: 1, 2 or 4.
size_t DTypeSize(DType dtype);
// "uint8", "float16", "float32".
const char* DTypeName(DType dtype);

// An IEEE 754 binary16 value, kept as its bit pattern (C++17 has no half).
struct Half {
  uint16_t bits = 0;
};
inline bool operator==(Half a, Half b) { return a.bits == b.bits; }
inline bool operator!=(Half a, Half b) { return a.bits != b.bits; }

// float -> binary16 with round-to-nearest-even; overflow gives +-inf, NaN
// stays NaN. binary16 -> float is exact.
Half FloatToHalf(float value);
float HalfToFloat(Half value);

// An owning interleaved image. Image8(w, h, c) is zero-filled.
template <typename T>
struct ImageT {
  int width = 0;
  int height = 0;
  int channels = 0;
  std::vector<T> pixels;  // width * height * channels elements

  ImageT() = default;
  ImageT(int w, int h, int c) : width(w), height(h), channels(c), pixels(size_t(w) * h * c, T{}) {}

  T& at(int x, int y, int c) { return pixels[(size_t(y) * width + x) * channels + c]; }
  const T& at(int x, int y, int c) const { return pixels[(size_t(y) * width + x) * channels + c]; }
  bool empty() const { return pixels.empty(); }
  size_t element_count() const { return pixels.size(); }

  friend bool operator==(const ImageT& a, const ImageT& b) {
    return a.width == b.width && a.height == b.height && a.channels == b.channels &&
           a.pixels == b.pixels;
  }
  friend bool operator!=(const ImageT& a, const ImageT& b) { return !(a == b); }
};

using Image8 = ImageT<uint8_t>;  // what PNG and JPEG hold
using ImageF16 = ImageT<Half>;
using ImageF = ImageT<float>;  // what EXR, metrics and conversions use

// One of the three, e.g. a dataset buffer read from PNG (Image8) or EXR
// (ImageF).
using AnyImage = std::variant<Image8, ImageF16, ImageF>;

// A read-only view of interleaved pixels owned by the caller. It never copies
// and must not outlive the pixels. Used for every image the SDK sends: the
// pixels are copied exactly once, into the request message.
struct ImageView {
  const void* data = nullptr;
  int width = 0;
  int height = 0;
  // Interleaved elements per pixel in memory.
  int channels = 0;
  DType dtype = DType::kUint8;
  // Bytes from the start of one row to the next; 0 means tightly packed
  // (width * channels * DTypeSize(dtype)). Lets an engine pass padded rows.
  size_t row_stride_bytes = 0;
  // For one-channel fields (depth, roughness, metallic) only: which channel
  // of a multi-channel view to send, e.g. 1 for roughness packed into the G
  // channel of an occlusion/roughness/metallic texture. -1: the view must
  // have exactly one channel.
  int select_channel = -1;

  bool empty() const { return data == nullptr; }
  // Bytes of one row's pixels (without padding) and from row to row.
  size_t packed_row_bytes() const { return size_t(width) * channels * DTypeSize(dtype); }
  size_t row_stride() const {
    return row_stride_bytes != 0 ? row_stride_bytes : packed_row_bytes();
  }
  const uint8_t* row(int y) const {
    return static_cast<const uint8_t*>(data) + size_t(y) * row_stride();
  }

  // Views of owning images (tightly packed).
  static ImageView Of(const Image8& image);
  static ImageView Of(const ImageF16& image);
  static ImageView Of(const ImageF& image);
  static ImageView Of(const AnyImage& image);
  // A view of raw caller memory.
  static ImageView Raw(const void* data, int width, int height, int channels, DType dtype,
                       size_t row_stride_bytes = 0);
};

// The dtype of an AnyImage and its shape.
DType DTypeOf(const AnyImage& image);
int WidthOf(const AnyImage& image);
int HeightOf(const AnyImage& image);
int ChannelsOf(const AnyImage& image);

// Conversions between element types (all channels of the view; the view's
// select_channel is ignored). uint8 -> float divides by 255; float -> uint8
// clamps to [0, 1], multiplies by 255 and rounds to nearest (NaN -> 0);
// float16 <-> float32 as FloatToHalf/HalfToFloat. An empty view gives an
// empty image.
ImageF ToFloat(const ImageView& view);
Image8 ToUint8(const ImageView& view);
ImageF16 ToHalf(const ImageView& view);
AnyImage ConvertTo(const ImageView& view, DType dtype);
inline ImageF ToFloat(const AnyImage& image) { return ToFloat(ImageView::Of(image)); }
inline Image8 ToUint8(const AnyImage& image) { return ToUint8(ImageView::Of(image)); }

// Channel-count conversions, as PIL's Image.convert does for the authors'
// dataset reader: ToGray uses ITU-R 601 luma (0.299, 0.587, 0.114; for uint8
// PIL's fixed-point (19595 R + 38470 G + 7471 B + 32768) >> 16); ToRgb
// replicates a gray channel. Images that already have the wanted channel
// count are returned unchanged; 4-channel images lose their alpha first.
Image8 ToGray(const Image8& image);
ImageF ToGray(const ImageF& image);
Image8 ToRgb(const Image8& image);
ImageF ToRgb(const ImageF& image);
AnyImage ToChannels(const AnyImage& image, int channels);  // channels 1 or 3

}  // namespace fd::client

#endif  // FD_CLIENT_SDK_IMAGE_H_

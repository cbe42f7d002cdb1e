#include "client_sdk/image.h"

#include <algorithm>
#include <cmath>
#include <cstring>

namespace fd::client {
namespace {

uint32_t FloatBits(float value) {
  uint32_t bits;
  std::memcpy(&bits, &value, sizeof(bits));
  return bits;
}

float BitsToFloat(uint32_t bits) {
  float value;
  std::memcpy(&value, &bits, sizeof(value));
  return value;
}

// Reads element i of a row as float, whatever the view's dtype.
float LoadAsFloat(const uint8_t* row, size_t i, DType dtype) {
  switch (dtype) {
    case DType::kUint8:
      return row[i] / 255.0f;
    case DType::kFloat16: {
      Half h;
      std::memcpy(&h.bits, row + 2 * i, 2);
      return HalfToFloat(h);
    }
    case DType::kFloat32: {
      float f;
      std::memcpy(&f, row + 4 * i, 4);
      return f;
    }
  }
  return 0.0f;
}

uint8_t FloatToUint8(float value) {
  if (!(value > 0.0f)) return 0;  // also NaN
  if (value >= 1.0f) return 255;
  return static_cast<uint8_t>(std::lround(value * 255.0f));
}

template <typename T>
ImageT<T> ConvertView(const ImageView& view, T (*convert)(float)) {
  if (view.empty()) return {};
  ImageT<T> out(view.width, view.height, view.channels);
  const size_t row_elements = size_t(view.width) * view.channels;
  for (int y = 0; y < view.height; ++y) {
    const uint8_t* row = view.row(y);
    T* dst = out.pixels.data() + size_t(y) * row_elements;
    for (size_t i = 0; i < row_elements; ++i) dst[i] = convert(LoadAsFloat(row, i, view.dtype));
  }
  return out;
}

// Copies a view whose dtype equals T without conversion (handles strides).
template <typename T>
ImageT<T> CopyView(const ImageView& view) {
  ImageT<T> out(view.width, view.height, view.channels);
  const size_t row_bytes = view.packed_row_bytes();
  for (int y = 0; y < view.height; ++y) {
    std::memcpy(reinterpret_cast<uint8_t*>(out.pixels.data()) + size_t(y) * row_bytes, view.row(y),
                row_bytes);
  }
  return out;
}

template <typename T>
ImageT<T> DropAlpha(const ImageT<T>& image) {
  ImageT<T> out(image.width, image.height, 3);
  for (size_t p = 0; p < size_t(image.width) * image.height; ++p) {
    for (int c = 0; c < 3; ++c) out.pixels[p * 3 + c] = image.pixels[p * 4 + c];
  }
  return out;
}

template <typename T>
ImageT<T> Replicate(const ImageT<T>& image) {
  ImageT<T> out(image.width, image.height, 3);
  for (size_t p = 0; p < size_t(image.width) * image.height; ++p) {
    for (int c = 0; c < 3; ++c) out.pixels[p * 3 + c] = image.pixels[p];
  }
  return out;
}

}  // namespace

size_t DTypeSize(DType dtype) {
  switch (dtype) {
    case DType::kUint8:
      return 1;
    case DType::kFloat16:
      return 2;
    case DType::kFloat32:
      return 4;
  }
  return 1;
}

const char* DTypeName(DType dtype) {
  switch (dtype) {
    case DType::kUint8:
      return "uint8";
    case DType::kFloat16:
      return "float16";
    case DType::kFloat32:
      return "float32";
  }
  return "?";
}

Half FloatToHalf(float value) {
  const uint32_t bits = FloatBits(value);
  const uint16_t sign = static_cast<uint16_t>((bits >> 16) & 0x8000u);
  const uint32_t magnitude = bits & 0x7fffffffu;
  if (magnitude >= 0x7f800000u) {  // inf or NaN (keep NaN quiet and non-zero)
    const uint16_t nan = magnitude > 0x7f800000u ? 0x0200u | ((magnitude >> 13) & 0x3ffu) : 0u;
    return Half{static_cast<uint16_t>(sign | 0x7c00u | nan)};
  }
  if (magnitude >= 0x477ff000u) {  // >= 65520 rounds past the largest half (65504)
    return Half{static_cast<uint16_t>(sign | 0x7c00u)};
  }
  if (magnitude < 0x38800000u) {  // below 2^-14: subnormal half, units of 2^-24
    // Exact scaling by a power of two, then round-half-even (default mode).
    const float units = std::nearbyint(BitsToFloat(magnitude) * 16777216.0f);
    return Half{static_cast<uint16_t>(sign | static_cast<uint16_t>(units))};
  }
  // Normal: rebias the exponent (127 -> 15) and round the 13 dropped mantissa
  // bits to nearest even; a carry correctly bumps the exponent.
  uint32_t rebiased = magnitude - 0x38000000u;
  rebiased += 0x0fffu + ((rebiased >> 13) & 1u);
  return Half{static_cast<uint16_t>(sign | (rebiased >> 13))};
}

float HalfToFloat(Half value) {
  const uint32_t sign = uint32_t(value.bits & 0x8000u) << 16;
  const uint32_t exponent = (value.bits >> 10) & 0x1fu;
  const uint32_t mantissa = value.bits & 0x3ffu;
  if (exponent == 0) {
    const float magnitude = static_cast<float>(mantissa) * (1.0f / 16777216.0f);
    return sign != 0 ? -magnitude : magnitude;
  }
  if (exponent == 31) return BitsToFloat(sign | 0x7f800000u | (mantissa << 13));
  return BitsToFloat(sign | ((exponent + 112u) << 23) | (mantissa << 13));
}

ImageView ImageView::Of(const Image8& image) {
  return Raw(image.pixels.data(), image.width, image.height, image.channels, DType::kUint8);
}
ImageView ImageView::Of(const ImageF16& image) {
  return Raw(image.pixels.data(), image.width, image.height, image.channels, DType::kFloat16);
}
ImageView ImageView::Of(const ImageF& image) {
  return Raw(image.pixels.data(), image.width, image.height, image.channels, DType::kFloat32);
}
ImageView ImageView::Of(const AnyImage& image) {
  return std::visit([](const auto& typed) { return ImageView::Of(typed); }, image);
}

ImageView ImageView::Raw(const void* data, int width, int height, int channels, DType dtype,
                         size_t row_stride_bytes) {
  ImageView view;
  // An empty owning image gives an empty view (data == nullptr).
  view.data = (width > 0 && height > 0 && channels > 0) ? data : nullptr;
  view.width = width;
  view.height = height;
  view.channels = channels;
  view.dtype = dtype;
  view.row_stride_bytes = row_stride_bytes;
  return view;
}

DType DTypeOf(const AnyImage& image) {
  switch (image.index()) {
    case 0:
      return DType::kUint8;
    case 1:
      return DType::kFloat16;
    default:
      return DType::kFloat32;
  }
}
int WidthOf(const AnyImage& image) {
  return std::visit([](const auto& typed) { return typed.width; }, image);
}
int HeightOf(const AnyImage& image) {
  return std::visit([](const auto& typed) { return typed.height; }, image);
}
int ChannelsOf(const AnyImage& image) {
  return std::visit([](const auto& typed) { return typed.channels; }, image);
}

ImageF ToFloat(const ImageView& view) {
  if (view.empty()) return {};
  if (view.dtype == DType::kFloat32) return CopyView<float>(view);
  return ConvertView<float>(view, [](float v) { return v; });
}

Image8 ToUint8(const ImageView& view) {
  if (view.empty()) return {};
  if (view.dtype == DType::kUint8) return CopyView<uint8_t>(view);
  return ConvertView<uint8_t>(view, &FloatToUint8);
}

ImageF16 ToHalf(const ImageView& view) {
  if (view.empty()) return {};
  if (view.dtype == DType::kFloat16) return CopyView<Half>(view);
  return ConvertView<Half>(view, &FloatToHalf);
}

AnyImage ConvertTo(const ImageView& view, DType dtype) {
  switch (dtype) {
    case DType::kUint8:
      return ToUint8(view);
    case DType::kFloat16:
      return ToHalf(view);
    case DType::kFloat32:
      return ToFloat(view);
  }
  return ToFloat(view);
}

Image8 ToGray(const Image8& image) {
  if (image.channels == 1) return image;
  const Image8 rgb = image.channels == 4 ? DropAlpha(image) : image;
  Image8 out(rgb.width, rgb.height, 1);
  for (size_t p = 0; p < out.pixels.size(); ++p) {
    const uint32_t r = rgb.pixels[3 * p], g = rgb.pixels[3 * p + 1], b = rgb.pixels[3 * p + 2];
    out.pixels[p] = static_cast<uint8_t>((r * 19595u + g * 38470u + b * 7471u + 0x8000u) >> 16);
  }
  return out;
}

ImageF ToGray(const ImageF& image) {
  if (image.channels == 1) return image;
  const ImageF rgb = image.channels == 4 ? DropAlpha(image) : image;
  ImageF out(rgb.width, rgb.height, 1);
  for (size_t p = 0; p < out.pixels.size(); ++p) {
    out.pixels[p] = 0.299f * rgb.pixels[3 * p] + 0.587f * rgb.pixels[3 * p + 1] +
                    0.114f * rgb.pixels[3 * p + 2];
  }
  return out;
}

Image8 ToRgb(const Image8& image) {
  if (image.channels == 3) return image;
  return image.channels == 4 ? DropAlpha(image) : Replicate(image);
}

ImageF ToRgb(const ImageF& image) {
  if (image.channels == 3) return image;
  return image.channels == 4 ? DropAlpha(image) : Replicate(image);
}

AnyImage ToChannels(const AnyImage& image, int channels) {
  if (ChannelsOf(image) == channels) return image;
  if (const auto* u8 = std::get_if<Image8>(&image)) {
    return channels == 1 ? ToGray(*u8) : ToRgb(*u8);
  }
  // float16 goes through float32 and back.
  const bool half = std::holds_alternative<ImageF16>(image);
  ImageF f = ToFloat(image);
  f = channels == 1 ? ToGray(f) : ToRgb(f);
  if (half) return ToHalf(ImageView::Of(f));
  return f;
}

}  // namespace fd::client

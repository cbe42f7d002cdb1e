// ImageBuffer: the pixels that cross component boundaries (wire decoder ->
// session -> model input; model output -> session state -> wire encoder)
// without LibTorch and without copies.
//
// Row-major HWC, `channels` elements per pixel, of one element type. The
// bytes are owned by a reference count and immutable once the buffer is
// shared: a decoder fills a fresh buffer through mutable_data() while it is
// the only holder, then hands out copies (which share the bytes). A buffer
// can also wrap bytes that something else keeps alive (a tensor's storage),
// so the session can keep the model's output as its "previous frame" and the
// stream can encode the same bytes.
//
// Value type: copying shares the bytes. Thread-safety: const methods are
// safe concurrently (the bytes never change after sharing); mutable_data()
// only before the buffer is shared.
#ifndef FD_BASE_IMAGE_BUFFER_H_
#define FD_BASE_IMAGE_BUFFER_H_

#include <cstddef>
#include <cstdint>
#include <cstring>
#include <memory>
#include <string_view>

#include "absl/types/span.h"

namespace fd {

enum class PixelType : uint8_t {
  kUint8 = 1,    // 0..255
  kFloat32 = 2,  // [0, 1]
};

inline size_t PixelTypeSize(PixelType type) { return type == PixelType::kFloat32 ? 4 : 1; }
inline std::string_view PixelTypeName(PixelType type) {
  return type == PixelType::kFloat32 ? "float32" : "uint8";
}

class ImageBuffer {
 public:
  // An empty buffer (no pixels): "not given".
  ImageBuffer() = default;

  // A new zero-filled buffer of width x height x channels elements.
  // Allocation failure throws std::bad_alloc like any container; callers
  // bound the sizes first (untrusted sizes never reach here unchecked).
  ImageBuffer(uint32_t width, uint32_t height, uint32_t channels, PixelType type)
      : width_(width), height_(height), channels_(channels), type_(type) {
    const size_t bytes = size_bytes();
    std::shared_ptr<uint8_t[]> storage(new uint8_t[bytes]());
    data_ = storage.get();
    owner_ = std::move(storage);
  }

  // Wraps `data` (size_bytes() bytes) that `owner` keeps alive, e.g. a
  // tensor's storage; nothing is copied. The bytes must not change while any
  // copy of the buffer lives.
  static ImageBuffer Wrap(uint32_t width, uint32_t height, uint32_t channels, PixelType type,
                          const void* data, std::shared_ptr<const void> owner) {
    ImageBuffer buffer;
    buffer.width_ = width;
    buffer.height_ = height;
    buffer.channels_ = channels;
    buffer.type_ = type;
    buffer.data_ = static_cast<const uint8_t*>(data);
    buffer.owner_ = std::move(owner);
    buffer.writable_ = false;
    return buffer;
  }

  bool empty() const { return data_ == nullptr; }
  uint32_t width() const { return width_; }
  uint32_t height() const { return height_; }
  uint32_t channels() const { return channels_; }
  PixelType type() const { return type_; }
  size_t num_elements() const { return size_t{width_} * height_ * channels_; }
  size_t size_bytes() const { return num_elements() * PixelTypeSize(type_); }

  // The raw bytes (size_bytes() of them).
  const uint8_t* data() const { return data_; }
  absl::Span<const uint8_t> bytes() const { return {data_, empty() ? 0 : size_bytes()}; }
  // The elements; requires type() == kUint8 / kFloat32 respectively.
  absl::Span<const uint8_t> uint8_elements() const { return bytes(); }
  absl::Span<const float> float_elements() const {
    return {reinterpret_cast<const float*>(data_), empty() ? 0 : num_elements()};
  }

  // For filling a buffer created by the sizing constructor, before it is
  // copied or shared. Null for an empty or wrapped buffer.
  uint8_t* mutable_data() { return owns_writable() ? const_cast<uint8_t*>(data_) : nullptr; }
  float* mutable_floats() { return reinterpret_cast<float*>(mutable_data()); }

  // Keeps the bytes alive (for wrapping them into another owner, e.g. a
  // tensor that must not outlive them).
  const std::shared_ptr<const void>& owner() const { return owner_; }

  bool SameShape(const ImageBuffer& other) const {
    return width_ == other.width_ && height_ == other.height_ && channels_ == other.channels_ &&
           type_ == other.type_;
  }

  // Deep equality: the same shape, type and bytes (or both empty).
  friend bool operator==(const ImageBuffer& a, const ImageBuffer& b) {
    if (a.empty() || b.empty()) return a.empty() == b.empty();
    return a.SameShape(b) && std::memcmp(a.data_, b.data_, a.size_bytes()) == 0;
  }
  friend bool operator!=(const ImageBuffer& a, const ImageBuffer& b) { return !(a == b); }

 private:
  bool owns_writable() const { return data_ != nullptr && owner_.use_count() == 1 && writable_; }

  uint32_t width_ = 0;
  uint32_t height_ = 0;
  uint32_t channels_ = 0;
  PixelType type_ = PixelType::kUint8;
  const uint8_t* data_ = nullptr;
  std::shared_ptr<const void> owner_;
  bool writable_ = true;  // false for wrapped bytes
};

}  // namespace fd

#endif  // FD_BASE_IMAGE_BUFFER_H_

#include "tools/scenegen/encoding.h"

#include <algorithm>
#include <cmath>

namespace fd::scenegen {

int BufferChannels(Buffer buffer) {
  switch (buffer) {
    case Buffer::kFinalImage:
    case Buffer::kBaseColor:
    case Buffer::kNormals:
      return 3;
    case Buffer::kDepth:
    case Buffer::kRoughness:
    case Buffer::kMetallic:
      return 1;
  }
  return 1;
}

float ToneMapAces(float x) {
  x = std::max(x, 0.0f);
  return Clamp01((x * (2.51f * x + 0.03f)) / (x * (2.43f * x + 0.59f) + 0.14f));
}

float LinearToSrgb(float x) {
  x = Clamp01(x);
  return x <= 0.0031308f ? 12.92f * x : 1.055f * std::pow(x, 1.0f / 2.4f) - 0.055f;
}

uint8_t ToByte(float unit) { return static_cast<uint8_t>(std::lround(Clamp01(unit) * 255.0f)); }

uint8_t EncodeDepth(float view_depth, float near_plane) {
  if (!(view_depth > 0.0f)) return 0;
  return std::max(kMinGeometryDepthByte, ToByte(near_plane / view_depth));
}

uint8_t EncodeNormalComponent(float n) { return ToByte(n * 0.5f + 0.5f); }

EncodedFrame EncodeFrame(const FrameBuffers& b, const EncodingParams& params) {
  EncodedFrame out;
  for (int k = 0; k < kNumBuffers; ++k) {
    out[k] = Image8(b.width, b.height, BufferChannels(static_cast<Buffer>(k)));
  }
  Image8& final_image = out[static_cast<int>(Buffer::kFinalImage)];
  Image8& base_color = out[static_cast<int>(Buffer::kBaseColor)];
  Image8& normals = out[static_cast<int>(Buffer::kNormals)];
  Image8& depth = out[static_cast<int>(Buffer::kDepth)];
  Image8& roughness = out[static_cast<int>(Buffer::kRoughness)];
  Image8& metallic = out[static_cast<int>(Buffer::kMetallic)];
  for (int y = 0; y < b.height; ++y) {
    for (int x = 0; x < b.width; ++x) {
      const size_t i = b.Index(x, y);
      const Vec3 c = b.radiance[i] * params.exposure;
      final_image.at(x, y, 0) = ToByte(LinearToSrgb(ToneMapAces(c.x)));
      final_image.at(x, y, 1) = ToByte(LinearToSrgb(ToneMapAces(c.y)));
      final_image.at(x, y, 2) = ToByte(LinearToSrgb(ToneMapAces(c.z)));
      if (!b.geometry[i]) continue;  // every G-buffer stays 0 for sky
      const Vec3& a = b.base_color[i];
      base_color.at(x, y, 0) = ToByte(LinearToSrgb(a.x));
      base_color.at(x, y, 1) = ToByte(LinearToSrgb(a.y));
      base_color.at(x, y, 2) = ToByte(LinearToSrgb(a.z));
      const Vec3& n = b.normal[i];
      normals.at(x, y, 0) = EncodeNormalComponent(n.x);
      normals.at(x, y, 1) = EncodeNormalComponent(n.y);
      normals.at(x, y, 2) = EncodeNormalComponent(n.z);
      depth.at(x, y, 0) = EncodeDepth(b.view_depth[i], params.near_plane);
      roughness.at(x, y, 0) = ToByte(b.roughness[i]);
      metallic.at(x, y, 0) = ToByte(b.metallic[i]);
    }
  }
  return out;
}

FloatFrame FloatFrameFromBuffers(const FrameBuffers& b, const EncodingParams& params) {
  FloatFrame out;
  for (int k = 0; k < kNumBuffers; ++k) {
    out[k] = ImageF(b.width, b.height, BufferChannels(static_cast<Buffer>(k)));
  }
  for (int y = 0; y < b.height; ++y) {
    for (int x = 0; x < b.width; ++x) {
      const size_t i = b.Index(x, y);
      const Vec3 c = b.radiance[i] * params.exposure;
      ImageF& final_image = out[static_cast<int>(Buffer::kFinalImage)];
      final_image.at(x, y, 0) = c.x;
      final_image.at(x, y, 1) = c.y;
      final_image.at(x, y, 2) = c.z;
      if (!b.geometry[i]) continue;
      for (int ch = 0; ch < 3; ++ch) {
        out[static_cast<int>(Buffer::kBaseColor)].at(x, y, ch) = b.base_color[i][ch];
        out[static_cast<int>(Buffer::kNormals)].at(x, y, ch) = b.normal[i][ch];
      }
      out[static_cast<int>(Buffer::kDepth)].at(x, y, 0) = params.near_plane / b.view_depth[i];
      out[static_cast<int>(Buffer::kRoughness)].at(x, y, 0) = b.roughness[i];
      out[static_cast<int>(Buffer::kMetallic)].at(x, y, 0) = b.metallic[i];
    }
  }
  return out;
}

}  // namespace fd::scenegen

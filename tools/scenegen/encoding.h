// Encoding of the rendered float buffers into the authors' dataset images.
//
// 8-bit PNG conventions (also written to scene.json):
//   FinalImage  RGB   ACES filmic tone map of exposure * radiance, then sRGB.
//   BaseColor   RGB   sRGB-encoded linear albedo; sky = (0, 0, 0).
//   Normals     RGB   world-space unit normal n (Z up) as round((n * 0.5 + 0.5) * 255);
//                     sky = (0, 0, 0).
//   Depth       gray  inverse depth round(255 * min(1, near / d)), d = view depth
//                     (metres along the camera axis), near = scene near plane;
//                     sky = 0. Geometry is never below kMinGeometryDepthByte
//                     (10): surfaces farther than near * 25.5 are stored as 10,
//                     so the reference's sky test (BaseColor < 10 and
//                     Depth < 10) never fires on geometry.
//   Roughness   gray  round(255 * roughness), linear; sky = 0.
//   Metallic    gray  round(255 * metallic), linear; sky = 0.
// Float EXR conventions: FinalImage = exposure * radiance (linear, before tone
// mapping; applying ToneMapAces and sRGB gives the PNG), BaseColor = linear
// albedo, Normals = raw n in [-1, 1], Depth = near / d without clamping or
// quantisation (metric depth = near / value), Roughness and Metallic linear;
// sky = 0 everywhere.
#ifndef FD_TOOLS_SCENEGEN_ENCODING_H_
#define FD_TOOLS_SCENEGEN_ENCODING_H_

#include <array>
#include <cstdint>

#include "client_sdk/image_io.h"
#include "tools/scenegen/renderer.h"

namespace fd::scenegen {

// Images and their PNG/EXR files come from the shared client I/O library.
using ::fd::client::Image8;
using ::fd::client::ImageF;
using ::fd::client::ReadExr;
using ::fd::client::ReadPng;
using ::fd::client::WriteExr;
using ::fd::client::WritePng;

// The dataset's buffer folders, in the order the reference stacks them after
// the final image.
enum class Buffer : int { kFinalImage, kBaseColor, kNormals, kDepth, kRoughness, kMetallic };
inline constexpr int kNumBuffers = 6;
inline constexpr std::array<const char*, kNumBuffers> kBufferNames = {
    "FinalImage", "BaseColor", "Normals", "Depth", "Roughness", "Metallic"};
// 3 for colour buffers, 1 for scalar buffers.
int BufferChannels(Buffer buffer);

// Smallest depth byte any geometry pixel gets (the far-plane clamp).
inline constexpr uint8_t kMinGeometryDepthByte = 10;

struct EncodingParams {
  float exposure = 1.0f;
  float near_plane = 1.0f;
};

// Scalar conversions (exposed for tests and documentation).
float ToneMapAces(float x);   // Narkowicz 2015 fit, maps [0, inf) to [0, 1)
float LinearToSrgb(float x);  // IEC 61966-2-1 OETF on [0, 1]
uint8_t ToByte(float unit);   // round(clamp(unit, 0, 1) * 255)
uint8_t EncodeDepth(float view_depth, float near_plane);  // 0 for view_depth <= 0
uint8_t EncodeNormalComponent(float n);

using EncodedFrame = std::array<Image8, kNumBuffers>;
using FloatFrame = std::array<ImageF, kNumBuffers>;

// Pure functions of the buffers; thread-safe.
EncodedFrame EncodeFrame(const FrameBuffers& buffers, const EncodingParams& params);
FloatFrame FloatFrameFromBuffers(const FrameBuffers& buffers, const EncodingParams& params);

}  // namespace fd::scenegen

#endif  // FD_TOOLS_SCENEGEN_ENCODING_H_

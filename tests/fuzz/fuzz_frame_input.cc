// Fuzz target: the bytes of a wire FrameInput (what a client streams each
// frame) -> server::DecodeFrameInput, the validation and decoding of the
// image planes (dtypes, zstd, sizes, NaN/Inf) before a frame reaches a
// session.
//
// Input: byte 0 picks the session (width and height 8..32, sky mode client
// image or off), the rest is a serialized framediffuser.v1.FrameInput.
// Properties: a decoded frame has exactly the session's shapes (3 or 1
// channels) with float values in [0, 1]; an error is INVALID_ARGUMENT naming
// a "frame." field, bounded in size.
#include <cmath>
#include <cstddef>
#include <cstdint>

#include "framediffuser/v1/render_service.pb.h"
#include "server/frame_input.h"
#include "tests/fuzz/fuzz_check.h"

namespace {

using fd::ImageBuffer;

void CheckPlane(const ImageBuffer& plane, const fd::session::SessionSettings& settings,
                uint32_t channels) {
  FD_FUZZ_CHECK(!plane.empty(), "plane present");
  FD_FUZZ_CHECK(plane.width() == settings.width && plane.height() == settings.height, "size");
  FD_FUZZ_CHECK(plane.channels() == channels, "channels");
  if (plane.type() == fd::PixelType::kFloat32) {
    for (float value : plane.float_elements()) {
      FD_FUZZ_CHECK(std::isfinite(value) && value >= 0.0f && value <= 1.0f, "value in [0, 1]");
    }
  }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size < 1) return 0;
  fd::session::SessionSettings settings;
  settings.environment = "fuzz";
  settings.width = 8u * (1u + (data[0] & 3u));
  settings.height = 8u * (1u + ((data[0] >> 2) & 3u));
  settings.steps = 1;
  settings.sky_mode =
      (data[0] & 16u) ? fd::session::SkyMode::kClientImage : fd::session::SkyMode::kOff;

  framediffuser::v1::FrameInput frame;
  if (!frame.ParseFromArray(data + 1, static_cast<int>(size - 1))) return 0;

  absl::StatusOr<fd::server::DecodedFrame> decoded = fd::server::DecodeFrameInput(frame, settings);
  if (!decoded.ok()) {
    fd::fuzz::CheckError(decoded.status(), absl::StatusCode::kInvalidArgument, "frame.");
    return 0;
  }
  const fd::session::FrameGBuffer& g = decoded->gbuffer;
  CheckPlane(g.basecolor, settings, 3);
  CheckPlane(g.normals, settings, 3);
  CheckPlane(g.depth, settings, 1);
  CheckPlane(g.roughness, settings, 1);
  if (!g.metallic.empty()) CheckPlane(g.metallic, settings, 1);
  if (settings.sky_mode == fd::session::SkyMode::kClientImage) {
    CheckPlane(g.sky, settings, 3);
  } else {
    FD_FUZZ_CHECK(g.sky.empty(), "sky ignored unless client_image");
  }
  if (decoded->reseed.has_value()) {
    CheckPlane(decoded->reseed->frame, settings, 3);
    if (!decoded->reseed->basecolor.empty()) CheckPlane(decoded->reseed->basecolor, settings, 3);
  }
  return 0;
}

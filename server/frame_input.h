// FrameInput / OpenSession images -> what a session takes.
//
// Applies the per-field rules of render_service.proto on top of
// image_codec.h: which planes are required, their channel counts, that every
// image has the session's size, that the sky image is sent in sky mode
// client_image, and that a keyframe basecolor comes with a keyframe. Every
// error is INVALID_ARGUMENT naming the field ("frame.gbuffer.normals.channels:
// expected 3, got 1"), so the server answers a bad frame with a FrameError
// and keeps the stream open.
//
// Validate once, at the edge: this and image_codec.h are where a client's
// images are checked. Below, session::BuildPipelineInput only asserts;
// what still checks is what other code calls directly as a public API:
// model::FramePipeline::Begin (the trainer, tools/evaluate and tests feed it
// tensors), session::SessionState / Session (sizes of the images kept as
// state, the invariant of an exported blob) and session::BasecolorBuffer
// (guards its own writes).
#ifndef FD_SERVER_FRAME_INPUT_H_
#define FD_SERVER_FRAME_INPUT_H_

#include <cstdint>
#include <optional>
#include <vector>

#include "absl/status/statusor.h"
#include "framediffuser/v1/render_service.pb.h"
#include "server/image_codec.h"
#include "session/pipeline_input_builder.h"
#include "session/session.h"
#include "session/session_settings.h"

namespace fd::server {

// A FrameInput decoded for a session. Value type; shares its images.
struct DecodedFrame {
  // Images from DecodeImage (HWC, uint8 or float32 in [0, 1]): basecolor,
  // normals and sky 3 channels; depth, roughness and metallic 1 channel.
  // metallic is empty when absent (zeros), sky is empty unless the sky mode
  // is client_image (the field is ignored otherwise).
  session::FrameGBuffer gbuffer;
  // FrameInput.keyframe (+ keyframe_basecolor) as uint8 HWC RGB; an empty
  // basecolor means "this frame's own basecolor". nullopt: no re-seed.
  std::optional<session::Keyframe> reseed;
};

// Validates and decodes `frame` for a session running with `settings`
// (image size = settings.width x settings.height). Channels: basecolor,
// normals, sky, keyframe, keyframe_basecolor 3; depth, roughness, metallic 1.
// INVALID_ARGUMENT naming the field, e.g. "frame.gbuffer.basecolor:
// required", "frame.sky: required in sky mode client_image",
// "frame.keyframe_basecolor: needs frame.keyframe", or any DecodeImage error
// under "frame.<field>". Does not check frame_index (the session does).
// Thread-safety: pure function.
absl::StatusOr<DecodedFrame> DecodeFrameInput(const v1::FrameInput& frame,
                                              const session::SessionSettings& settings);

// OpenSession.keyframe / keyframe_basecolor, as uint8 HWC RGB bytes. Value
// type.
struct DecodedStartKeyframe {
  ImageBuffer frame;      // uint8 HWC RGB
  ImageBuffer basecolor;  // empty = the first frame's basecolor
};

// The session's start keyframe, checked against the session's size
// `width` x `height` (3 channels each). nullopt when no keyframe was sent.
// INVALID_ARGUMENT naming the field ("open.keyframe.width: expected 256, got
// 128", "open.keyframe_basecolor: needs open.keyframe", ...).
// Thread-safety: pure function.
absl::StatusOr<std::optional<DecodedStartKeyframe>> DecodeOpenKeyframe(const v1::OpenSession& open,
                                                                       uint32_t width,
                                                                       uint32_t height);

}  // namespace fd::server

#endif  // FD_SERVER_FRAME_INPUT_H_

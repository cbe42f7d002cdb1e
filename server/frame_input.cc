#include "server/frame_input.h"

#include <string>
#include <utility>

#include "absl/strings/str_cat.h"
#include "base/status_macros.h"

namespace fd::server {
namespace {

absl::Status Required(std::string_view field) {
  return absl::InvalidArgumentError(absl::StrCat(std::string(field), ": required"));
}

// A required image plane of the G-buffer.
absl::StatusOr<ImageBuffer> Plane(bool present, const v1::Image& image, std::string_view field,
                                  const ImageShape& shape) {
  if (!present) return Required(field);
  return DecodeImage(image, field, shape);
}

// keyframe (+ optional keyframe_basecolor) of a FrameInput or OpenSession,
// whose fields are named prefix + "keyframe" / "keyframe_basecolor".
absl::StatusOr<std::optional<session::Keyframe>> Keyframe(
    bool has_keyframe, const v1::Image& keyframe, bool has_basecolor, const v1::Image& basecolor,
    std::string_view prefix, const ImageShape& rgb) {
  const std::string keyframe_field = absl::StrCat(std::string(prefix), "keyframe");
  const std::string basecolor_field = absl::StrCat(std::string(prefix), "keyframe_basecolor");
  if (!has_keyframe) {
    if (has_basecolor) {
      return absl::InvalidArgumentError(absl::StrCat(basecolor_field, ": needs ", keyframe_field));
    }
    return std::nullopt;
  }
  session::Keyframe out;
  FD_ASSIGN_OR_RETURN(out.frame, DecodeImageBytes(keyframe, keyframe_field, rgb));
  if (has_basecolor) {
    FD_ASSIGN_OR_RETURN(out.basecolor, DecodeImageBytes(basecolor, basecolor_field, rgb));
  }
  return out;
}

}  // namespace

absl::StatusOr<DecodedFrame> DecodeFrameInput(const v1::FrameInput& frame,
                                              const session::SessionSettings& settings) {
  const ImageShape rgb{settings.width, settings.height, 3};
  const ImageShape gray{settings.width, settings.height, 1};
  if (!frame.has_gbuffer()) return Required("frame.gbuffer");
  const v1::GBuffer& g = frame.gbuffer();
  DecodedFrame out;
  FD_ASSIGN_OR_RETURN(out.gbuffer.basecolor,
                      Plane(g.has_basecolor(), g.basecolor(), "frame.gbuffer.basecolor", rgb));
  FD_ASSIGN_OR_RETURN(out.gbuffer.normals,
                      Plane(g.has_normals(), g.normals(), "frame.gbuffer.normals", rgb));
  FD_ASSIGN_OR_RETURN(out.gbuffer.depth,
                      Plane(g.has_depth(), g.depth(), "frame.gbuffer.depth", gray));
  FD_ASSIGN_OR_RETURN(out.gbuffer.roughness,
                      Plane(g.has_roughness(), g.roughness(), "frame.gbuffer.roughness", gray));
  if (g.has_metallic()) {
    FD_ASSIGN_OR_RETURN(out.gbuffer.metallic,
                        DecodeImage(g.metallic(), "frame.gbuffer.metallic", gray));
  }
  // The sky image is ignored in the other modes (render_service.proto), so
  // it is not decoded either.
  if (settings.sky_mode == session::SkyMode::kClientImage) {
    if (!frame.has_sky()) {
      return absl::InvalidArgumentError(
          absl::StrCat("frame.sky: required in sky mode ",
                       std::string(session::SkyModeName(settings.sky_mode))));
    }
    FD_ASSIGN_OR_RETURN(out.gbuffer.sky, DecodeImage(frame.sky(), "frame.sky", rgb));
  }
  FD_ASSIGN_OR_RETURN(
      out.reseed, Keyframe(frame.has_keyframe(), frame.keyframe(), frame.has_keyframe_basecolor(),
                           frame.keyframe_basecolor(), "frame.", rgb));
  return out;
}

absl::StatusOr<std::optional<DecodedStartKeyframe>> DecodeOpenKeyframe(const v1::OpenSession& open,
                                                                       uint32_t width,
                                                                       uint32_t height) {
  FD_ASSIGN_OR_RETURN(std::optional<session::Keyframe> keyframe,
                      Keyframe(open.has_keyframe(), open.keyframe(), open.has_keyframe_basecolor(),
                               open.keyframe_basecolor(), "open.", ImageShape{width, height, 3}));
  if (!keyframe.has_value()) return std::nullopt;
  DecodedStartKeyframe out;
  out.frame = std::move(keyframe->frame);
  out.basecolor = std::move(keyframe->basecolor);
  return out;
}

}  // namespace fd::server

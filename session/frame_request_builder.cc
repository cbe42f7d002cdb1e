#include "session/frame_request_builder.h"

#include <torch/torch.h>

#include <cstring>
#include <string>

#include "absl/strings/str_cat.h"
#include "model/status_macros.h"

namespace fd::session {
namespace {

// Copies a uint8 HWC RGB buffer of the session's size into a new tensor.
torch::Tensor ImageTensor(const SessionSettings& s, absl::Span<const uint8_t> pixels) {
  torch::Tensor t = torch::empty({static_cast<int64_t>(s.height), static_cast<int64_t>(s.width), 3},
                                 torch::kUInt8);
  std::memcpy(t.data_ptr<uint8_t>(), pixels.data(), pixels.size());
  return t;
}

// INVALID_ARGUMENT unless `t` is defined (or optional) and starts with
// [height, width].
absl::Status CheckPlane(const SessionSettings& s, const char* field, const torch::Tensor& t,
                        bool optional) {
  if (!t.defined()) {
    if (optional) return absl::OkStatus();
    return absl::InvalidArgumentError(absl::StrCat("gbuffer.", field, ": missing"));
  }
  if (t.dim() < 2 || t.size(0) != s.height || t.size(1) != s.width) {
    return absl::InvalidArgumentError(absl::StrCat("gbuffer.", field, ": expected ", s.height,
                                                   " x ", s.width, " (H x W ...), got ",
                                                   c10::str(t.sizes())));
  }
  return absl::OkStatus();
}

absl::Status CheckRgb(const SessionSettings& s, const char* field, const torch::Tensor& t) {
  FD_RETURN_IF_ERROR(CheckPlane(s, field, t, /*optional=*/false));
  if (t.dim() != 3 || t.size(2) != 3) {
    return absl::InvalidArgumentError(
        absl::StrCat("gbuffer.", field, ": expected [H, W, 3], got ", c10::str(t.sizes())));
  }
  return absl::OkStatus();
}

}  // namespace

model::SchedulerType ToModelScheduler(SchedulerKind kind) {
  switch (kind) {
    case SchedulerKind::kUniPC:
      return model::SchedulerType::kUniPCMultistep;
    case SchedulerKind::kDpmSolverPP2M:
      return model::SchedulerType::kDPMSolverMultistep;
    case SchedulerKind::kDDIM:
      return model::SchedulerType::kDDIM;
    case SchedulerKind::kEulerDiscrete:
      return model::SchedulerType::kEulerDiscrete;
  }
  return model::SchedulerType::kUniPCMultistep;
}

model::SkyFillMode ToModelSkyMode(SkyMode mode) {
  switch (mode) {
    case SkyMode::kClientImage:
      return model::SkyFillMode::kSkyImage;
    case SkyMode::kPreviousOutput:
      return model::SkyFillMode::kPreviousOutput;
    case SkyMode::kOff:
      return model::SkyFillMode::kNone;
  }
  return model::SkyFillMode::kNone;
}

absl::StatusOr<model::FrameRequest> BuildFrameRequest(const SessionSettings& settings,
                                                      const FrameContext& context,
                                                      const FrameGBuffer& gbuffer) {
  FD_RETURN_IF_ERROR(CheckRgb(settings, "basecolor", gbuffer.basecolor));
  FD_RETURN_IF_ERROR(CheckRgb(settings, "normals", gbuffer.normals));
  FD_RETURN_IF_ERROR(CheckPlane(settings, "depth", gbuffer.depth, /*optional=*/false));
  FD_RETURN_IF_ERROR(CheckPlane(settings, "roughness", gbuffer.roughness, /*optional=*/false));
  FD_RETURN_IF_ERROR(CheckPlane(settings, "metallic", gbuffer.metallic, /*optional=*/true));
  if (settings.sky_mode == SkyMode::kClientImage)
    FD_RETURN_IF_ERROR(CheckRgb(settings, "sky", gbuffer.sky));

  return model::TorchCall("BuildFrameRequest", [&]() -> absl::StatusOr<model::FrameRequest> {
    model::FrameRequest r;
    if (!context.previous_frame.empty()) {
      // Keyframe start, re-seed or the last output.
      r.previous_frame = ImageTensor(settings, context.previous_frame);
      // A keyframe sent without its basecolor: this frame's own basecolor.
      r.previous_basecolor = context.previous_basecolor.empty()
                                 ? gbuffer.basecolor
                                 : ImageTensor(settings, context.previous_basecolor);
    }
    // else: G-buffer-only start (black irradiance, zero previous latent).
    r.basecolor = gbuffer.basecolor;
    r.normals = gbuffer.normals;
    r.depth = gbuffer.depth;
    r.roughness = gbuffer.roughness;
    r.metallic = gbuffer.metallic;
    r.sky_mode = ToModelSkyMode(settings.sky_mode);
    if (settings.sky_mode == SkyMode::kClientImage) r.sky_image = gbuffer.sky;
    r.vae_noise_seed = VaeNoiseSeed(context.frame_seed);
    r.init_noise_seed = InitNoiseSeed(context.frame_seed);
    r.steps = static_cast<int>(settings.steps);
    r.scheduler = ToModelScheduler(settings.scheduler);
    r.want_float = settings.output_dtype != OutputDType::kUint8;
    return r;
  });
}

absl::StatusOr<std::vector<uint8_t>> BasecolorBytes(const SessionSettings& settings,
                                                    const torch::Tensor& basecolor) {
  FD_RETURN_IF_ERROR(CheckRgb(settings, "basecolor", basecolor));
  return model::TorchCall("BasecolorBytes", [&]() -> absl::StatusOr<std::vector<uint8_t>> {
    torch::Tensor u8 =
        basecolor.scalar_type() == torch::kUInt8
            ? basecolor
            : (basecolor.to(torch::kFloat32) * 255).round().clamp(0, 255).to(torch::kUInt8);
    u8 = u8.to(torch::kCPU).contiguous();
    const uint8_t* p = u8.data_ptr<uint8_t>();
    return std::vector<uint8_t>(p, p + u8.numel());
  });
}

absl::StatusOr<std::vector<uint8_t>> ImageBytes(const SessionSettings& settings,
                                                const torch::Tensor& image_uint8) {
  if (!image_uint8.defined() || image_uint8.scalar_type() != torch::kUInt8 ||
      image_uint8.dim() != 3 || image_uint8.size(0) != settings.height ||
      image_uint8.size(1) != settings.width || image_uint8.size(2) != 3) {
    return absl::InvalidArgumentError(
        "image_uint8: expected a uint8 [H, W, 3] tensor of the session's size");
  }
  return model::TorchCall("ImageBytes", [&]() -> absl::StatusOr<std::vector<uint8_t>> {
    const torch::Tensor c = image_uint8.to(torch::kCPU).contiguous();
    const uint8_t* p = c.data_ptr<uint8_t>();
    return std::vector<uint8_t>(p, p + c.numel());
  });
}

absl::StatusOr<std::vector<float>> FloatImageHwc(const SessionSettings& settings,
                                                 const torch::Tensor& image_float) {
  if (!image_float.defined() || image_float.scalar_type() != torch::kFloat32 ||
      image_float.dim() != 4 || image_float.size(0) != 1 || image_float.size(1) != 3 ||
      image_float.size(2) != settings.height || image_float.size(3) != settings.width) {
    return absl::InvalidArgumentError(
        "image_float: expected a float32 [1, 3, H, W] tensor of the session's size");
  }
  return model::TorchCall("FloatImageHwc", [&]() -> absl::StatusOr<std::vector<float>> {
    const torch::Tensor c = image_float[0].permute({1, 2, 0}).to(torch::kCPU).contiguous();
    const float* p = c.data_ptr<float>();
    return std::vector<float>(p, p + c.numel());
  });
}

}  // namespace fd::session

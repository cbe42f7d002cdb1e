#include "session/pipeline_input_builder.h"

#include <torch/torch.h>

#include <cassert>
#include <cmath>
#include <cstring>
#include <memory>
#include <string>

#include "absl/strings/str_cat.h"
#include "base/status_macros.h"
#include "model/runtime/torch_call.h"
#include "session/model_enums.h"

namespace fd::session {
namespace {

// INVALID_ARGUMENT unless `image` is given (or optional) and is the session's
// height x width with `channels` channels.
absl::Status CheckPlane(const SessionSettings& s, const char* field, const ImageBuffer& image,
                        uint32_t channels, bool optional) {
  if (image.empty()) {
    if (optional) return absl::OkStatus();
    return absl::InvalidArgumentError(absl::StrCat("gbuffer.", field, ": missing"));
  }
  if (image.height() != s.height || image.width() != s.width) {
    return absl::InvalidArgumentError(absl::StrCat("gbuffer.", field, ": expected ", s.height,
                                                   " x ", s.width, " (H x W ...), got ",
                                                   image.height(), " x ", image.width()));
  }
  if (image.channels() != channels) {
    return absl::InvalidArgumentError(absl::StrCat("gbuffer.", field, ": expected [H, W, ",
                                                   channels, "], got ", image.channels(),
                                                   " channels"));
  }
  return absl::OkStatus();
}

}  // namespace

torch::Tensor TensorView(const ImageBuffer& image) {
  if (image.empty()) return torch::Tensor();
  // from_blob with a deleter that holds the buffer's owner: the tensor keeps
  // the bytes alive. The cast drops const: the model never writes its inputs.
  std::shared_ptr<const void> owner = image.owner();
  return torch::from_blob(
      const_cast<uint8_t*>(image.data()),
      {static_cast<int64_t>(image.height()), static_cast<int64_t>(image.width()),
       static_cast<int64_t>(image.channels())},
      [owner](void*) mutable { owner.reset(); },
      torch::TensorOptions().dtype(image.type() == PixelType::kFloat32 ? torch::kFloat32
                                                                       : torch::kUInt8));
}

torch::Tensor LatentView(const LatentBuffer& latent) {
  if (latent.empty()) return torch::Tensor();
  std::shared_ptr<const std::vector<float>> owner = latent.values;
  return torch::from_blob(
      const_cast<float*>(owner->data()),
      {1, static_cast<int64_t>(latent.channels), static_cast<int64_t>(latent.height),
       static_cast<int64_t>(latent.width)},
      [owner](void*) mutable { owner.reset(); }, torch::TensorOptions().dtype(torch::kFloat32));
}

absl::StatusOr<LatentBuffer> OutputLatent(const torch::Tensor& latent) {
  if (!latent.defined() || latent.dim() != 4 || latent.size(0) != 1 ||
      latent.scalar_type() != torch::kFloat32) {
    return absl::InvalidArgumentError("latent: expected a float32 [1, C, h, w] tensor");
  }
  return model::TorchCall("OutputLatent", [&]() -> absl::StatusOr<LatentBuffer> {
    const torch::Tensor cpu = latent.to(torch::kCPU).contiguous();
    LatentBuffer out;
    out.channels = static_cast<uint32_t>(cpu.size(1));
    out.height = static_cast<uint32_t>(cpu.size(2));
    out.width = static_cast<uint32_t>(cpu.size(3));
    const float* data = cpu.data_ptr<float>();
    out.values = std::make_shared<const std::vector<float>>(data, data + cpu.numel());
    return out;
  });
}

absl::StatusOr<ImageBuffer> BufferFromTensor(const torch::Tensor& hwc) {
  if (!hwc.defined() || !hwc.device().is_cpu() || (hwc.dim() != 2 && hwc.dim() != 3) ||
      (hwc.scalar_type() != torch::kUInt8 && hwc.scalar_type() != torch::kFloat32)) {
    return absl::InvalidArgumentError(
        "image: expected a CPU uint8 or float32 [H, W, C] or [H, W] tensor");
  }
  return model::TorchCall("BufferFromTensor", [&]() -> absl::StatusOr<ImageBuffer> {
    const torch::Tensor c = hwc.contiguous();
    const PixelType type =
        c.scalar_type() == torch::kFloat32 ? PixelType::kFloat32 : PixelType::kUint8;
    // The buffer's owner holds a reference to the tensor's storage.
    auto keep = std::make_shared<torch::Tensor>(c);
    return ImageBuffer::Wrap(static_cast<uint32_t>(c.size(1)), static_cast<uint32_t>(c.size(0)),
                             c.dim() == 3 ? static_cast<uint32_t>(c.size(2)) : 1, type,
                             c.data_ptr(), std::shared_ptr<const void>(keep, keep.get()));
  });
}

absl::StatusOr<model::PipelineInput> BuildPipelineInput(const SessionSettings& settings,
                                                        const FrameContext& context,
                                                        const FrameGBuffer& gbuffer) {
  // Validated once, at the edge (server/frame_input.h); here only asserted.
  // A job built by other code with a wrong image still fails cleanly: the
  // model's Begin checks its (public) inputs and names the field.
  assert(CheckPlane(settings, "basecolor", gbuffer.basecolor, 3, false).ok());
  assert(CheckPlane(settings, "normals", gbuffer.normals, 3, false).ok());
  assert(CheckPlane(settings, "depth", gbuffer.depth, 1, false).ok());
  assert(CheckPlane(settings, "roughness", gbuffer.roughness, 1, false).ok());
  assert(CheckPlane(settings, "metallic", gbuffer.metallic, 1, true).ok());
  assert(settings.sky_mode != SkyMode::kClientImage ||
         CheckPlane(settings, "sky", gbuffer.sky, 3, false).ok());

  return model::TorchCall("BuildPipelineInput", [&]() -> absl::StatusOr<model::PipelineInput> {
    model::PipelineInput r;
    r.basecolor = TensorView(gbuffer.basecolor);
    if (!context.previous_frame.empty()) {
      // Keyframe start, re-seed or the last output.
      r.previous_frame = TensorView(context.previous_frame);
      // A keyframe sent without its basecolor: this frame's own basecolor.
      r.previous_basecolor =
          context.previous_basecolor.empty() ? r.basecolor : TensorView(context.previous_basecolor);
      // "previous_latent": "reuse": the last output's own latent instead of
      // the VAE encode of its image (which still gives the irradiance).
      r.prev_latent = LatentView(context.previous_latent);
    }
    // else: G-buffer-only start (black irradiance, zero previous latent).
    r.normals = TensorView(gbuffer.normals);
    r.depth = TensorView(gbuffer.depth);
    r.roughness = TensorView(gbuffer.roughness);
    r.metallic = TensorView(gbuffer.metallic);
    r.sky_mode = ToModelSkyMode(settings.sky_mode);
    if (settings.sky_mode == SkyMode::kClientImage) r.sky_image = TensorView(gbuffer.sky);
    r.vae_noise_seed = VaeNoiseSeed(context.frame_seed);
    r.init_noise_seed = InitNoiseSeed(context.frame_seed);
    r.steps = static_cast<int>(settings.steps);
    r.scheduler = ToModelScheduler(settings.scheduler);
    r.want_float = settings.output_dtype != OutputDType::kUint8;
    return r;
  });
}

absl::StatusOr<ImageBuffer> BasecolorBuffer(const SessionSettings& settings,
                                            const ImageBuffer& basecolor) {
  // Kept as a real check (not an assert): the quantisation below writes
  // width x height x 3 bytes.
  FD_RETURN_IF_ERROR(CheckPlane(settings, "basecolor", basecolor, 3, false));
  if (basecolor.type() == PixelType::kUint8) return basecolor;
  ImageBuffer out(basecolor.width(), basecolor.height(), 3, PixelType::kUint8);
  const absl::Span<const float> in = basecolor.float_elements();
  uint8_t* dst = out.mutable_data();
  for (size_t i = 0; i < in.size(); ++i) {
    // x * 255 in float32, rounded half to even, clamped to 0..255.
    const float v = std::nearbyint(in[i] * 255.0f);
    dst[i] = static_cast<uint8_t>(v < 0.0f ? 0.0f : (v > 255.0f ? 255.0f : v));
  }
  return out;
}

absl::StatusOr<ImageBuffer> OutputImage(const SessionSettings& settings,
                                        const torch::Tensor& image_uint8) {
  if (!image_uint8.defined() || image_uint8.scalar_type() != torch::kUInt8 ||
      image_uint8.dim() != 3 || image_uint8.size(0) != settings.height ||
      image_uint8.size(1) != settings.width || image_uint8.size(2) != 3) {
    return absl::InvalidArgumentError(
        "image_uint8: expected a uint8 [H, W, 3] tensor of the session's size");
  }
  FD_ASSIGN_OR_RETURN(torch::Tensor cpu, model::TorchCall("OutputImage", [&] {
                        return absl::StatusOr<torch::Tensor>(image_uint8.to(torch::kCPU));
                      }));
  return BufferFromTensor(cpu);
}

absl::StatusOr<ImageBuffer> OutputFloatImage(const SessionSettings& settings,
                                             const torch::Tensor& image_float) {
  if (!image_float.defined() || image_float.scalar_type() != torch::kFloat32 ||
      image_float.dim() != 4 || image_float.size(0) != 1 || image_float.size(1) != 3 ||
      image_float.size(2) != settings.height || image_float.size(3) != settings.width) {
    return absl::InvalidArgumentError(
        "image_float: expected a float32 [1, 3, H, W] tensor of the session's size");
  }
  FD_ASSIGN_OR_RETURN(torch::Tensor hwc, model::TorchCall("OutputFloatImage", [&] {
                        return absl::StatusOr<torch::Tensor>(
                            image_float[0].permute({1, 2, 0}).to(torch::kCPU).contiguous());
                      }));
  return BufferFromTensor(hwc);
}

}  // namespace fd::session

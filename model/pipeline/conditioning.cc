#include "model/pipeline/conditioning.h"

#include <torch/torch.h>

#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "base/status_macros.h"
#include "model/runtime/torch_call.h"

namespace fd::model {
namespace {

std::string Shape(const torch::Tensor& t) {
  return absl::StrCat("[", absl::StrJoin(t.sizes(), ", "), "]");
}

absl::Status Invalid(std::string_view name, std::string_view what) {
  return absl::InvalidArgumentError(absl::StrCat(std::string(name), ": ", std::string(what)));
}

// Rank, channels, dtype, spatial size (a positive multiple of
// `size_multiple`) and, for floating point images, finiteness and range.
// Does not check other inputs.
absl::Status CheckImage(const torch::Tensor& image, std::string_view name, int64_t channels,
                        int64_t size_multiple = 1) {
  if (!image.defined()) return Invalid(name, "is missing");
  if (image.dim() != 4) {
    return Invalid(name, absl::StrCat("must be [N, ", channels, ", H, W], got ", Shape(image)));
  }
  if (image.size(1) != channels) {
    return Invalid(name, absl::StrCat("must have ", channels, " channel(s), got ", image.size(1),
                                      " (shape ", Shape(image), ")"));
  }
  const int64_t h = image.size(2);
  const int64_t w = image.size(3);
  if (image.size(0) < 1 || h < 1 || w < 1) {
    return Invalid(name,
                   absl::StrCat("batch, height and width must be positive, got ", Shape(image)));
  }
  if (h % size_multiple != 0 || w % size_multiple != 0) {
    return Invalid(name,
                   absl::StrCat("height and width must be multiples of ", size_multiple,
                                " (the latent is 1/", size_multiple, " size), got ", h, "x", w));
  }
  if (image.scalar_type() == torch::kUInt8) return absl::OkStatus();
  if (!image.is_floating_point()) {
    return Invalid(name, absl::StrCat("must be uint8 or floating point in [0, 1], got ",
                                      std::string(c10::toString(image.scalar_type()))));
  }
  if (!torch::isfinite(image).all().item<bool>()) return Invalid(name, "contains NaN or Inf");
  if ((image < 0).any().item<bool>() || (image > 1).any().item<bool>()) {
    return Invalid(name, "floating-point values must be in [0, 1]");
  }
  return absl::OkStatus();
}

// `other` has the batch size, spatial size and device of `reference`.
absl::Status CheckSameGeometry(const torch::Tensor& other, std::string_view other_name,
                               const torch::Tensor& reference, std::string_view reference_name) {
  if (other.size(0) != reference.size(0) || other.size(2) != reference.size(2) ||
      other.size(3) != reference.size(3)) {
    return Invalid(other_name, absl::StrCat("shape ", Shape(other), " does not match ",
                                            std::string(reference_name), " ", Shape(reference),
                                            " (batch and H x W must agree)"));
  }
  if (other.device() != reference.device()) {
    return Invalid(other_name,
                   absl::StrCat("is on ", other.device().str(), " but ",
                                std::string(reference_name), " is on ", reference.device().str()));
  }
  return absl::OkStatus();
}

absl::Status CheckInput(const torch::Tensor& image, std::string_view name, int64_t channels,
                        const torch::Tensor& reference, std::string_view reference_name) {
  FD_RETURN_IF_ERROR(CheckImage(image, name, channels));
  return CheckSameGeometry(image, name, reference, reference_name);
}

// Already validated.
torch::Tensor AsUint8(const torch::Tensor& image) {
  if (image.scalar_type() == torch::kUInt8) return image;
  // As the pipeline turns its float output into the PIL image the reference
  // feeds back: (x * 255).round() (half to even) as uint8.
  return (image.to(torch::kFloat32) * 255.0).round().to(torch::kUInt8);
}

// ToTensor() + Normalize(0.5, 0.5): (u8 / 255 - 0.5) / 0.5 in float32.
torch::Tensor Normalize(const torch::Tensor& u8) {
  return (u8.to(torch::kFloat32).div(255.0) - 0.5) / 0.5;
}

// 0.299 R + 0.587 G + 0.114 B of u8 / 255, left to right, float32.
torch::Tensor Luma(const torch::Tensor& rgb_u8) {
  const torch::Tensor f = rgb_u8.to(torch::kFloat32) / 255.0;
  return 0.299 * f.select(1, 0) + 0.587 * f.select(1, 1) + 0.114 * f.select(1, 2);
}

torch::Tensor IrradianceOfValid(const torch::Tensor& final_u8, const torch::Tensor& albedo_u8) {
  const torch::Tensor final_grey = Luma(final_u8);
  const torch::Tensor albedo_grey = Luma(albedo_u8);
  const torch::Tensor valid = albedo_grey > 0.01;
  torch::Tensor irradiance =
      torch::where(valid, final_grey / (albedo_grey + 1e-6), torch::full_like(albedo_grey, 2.0));
  return (torch::clamp(irradiance, 0, 2) / 2.0).unsqueeze(1);
}

// (irradiance * 255) truncated, like numpy's astype(np.uint8).
torch::Tensor QuantizeIrradianceOfValid(const torch::Tensor& irradiance) {
  return (irradiance.to(torch::kFloat32) * 255.0).to(torch::kUInt8);
}

torch::Tensor FillSkyOfValid(const torch::Tensor& basecolor_u8, const torch::Tensor& depth_u8,
                             const torch::Tensor& sky_u8) {
  // mask = all(basecolor < 10 over channels) & depth < 10: [N, 1, H, W]
  const torch::Tensor mask =
      (basecolor_u8 < 10).all(1, /*keepdim=*/true).logical_and(depth_u8 < 10);
  return torch::where(mask, sky_u8, basecolor_u8);
}

absl::Status CheckGBuffer(const GBuffer& g, int64_t size_multiple) {
  if (size_multiple < 1) {
    return absl::InvalidArgumentError(
        absl::StrCat("size_multiple must be >= 1, got ", size_multiple));
  }
  FD_RETURN_IF_ERROR(CheckImage(g.basecolor, "basecolor", 3, size_multiple));
  FD_RETURN_IF_ERROR(CheckInput(g.normals, "normals", 3, g.basecolor, "basecolor"));
  FD_RETURN_IF_ERROR(CheckInput(g.depth, "depth", 1, g.basecolor, "basecolor"));
  FD_RETURN_IF_ERROR(CheckInput(g.roughness, "roughness", 1, g.basecolor, "basecolor"));
  if (g.metallic.defined()) {
    FD_RETURN_IF_ERROR(CheckInput(g.metallic, "metallic", 1, g.basecolor, "basecolor"));
  }
  return absl::OkStatus();
}

torch::Tensor PackOfValid(const GBuffer& g, const torch::Tensor& basecolor_u8,
                          const torch::Tensor& irradiance_u8) {
  const torch::Tensor metallic =
      g.metallic.defined() ? AsUint8(g.metallic) : torch::zeros_like(AsUint8(g.depth));
  return torch::cat(
      {Normalize(basecolor_u8), Normalize(AsUint8(g.normals)), Normalize(AsUint8(g.depth)),
       Normalize(AsUint8(g.roughness)), Normalize(metallic), Normalize(irradiance_u8)},
      1);
}

}  // namespace

absl::StatusOr<torch::Tensor> ToUint8Image(const torch::Tensor& image, std::string_view name,
                                           int64_t channels) {
  return TorchCall("ToUint8Image", [&]() -> absl::StatusOr<torch::Tensor> {
    FD_RETURN_IF_ERROR(CheckImage(image, name, channels));
    return AsUint8(image);
  });
}

absl::StatusOr<torch::Tensor> ComputeIrradiance(const torch::Tensor& final_rgb,
                                                const torch::Tensor& albedo_rgb) {
  return TorchCall("ComputeIrradiance", [&]() -> absl::StatusOr<torch::Tensor> {
    FD_RETURN_IF_ERROR(CheckImage(final_rgb, "irradiance final image", 3));
    FD_RETURN_IF_ERROR(
        CheckInput(albedo_rgb, "irradiance albedo", 3, final_rgb, "irradiance final image"));
    return IrradianceOfValid(AsUint8(final_rgb), AsUint8(albedo_rgb));
  });
}

absl::StatusOr<torch::Tensor> QuantizeIrradiance(const torch::Tensor& irradiance) {
  return TorchCall("QuantizeIrradiance", [&]() -> absl::StatusOr<torch::Tensor> {
    if (irradiance.defined() && irradiance.is_floating_point()) {
      FD_RETURN_IF_ERROR(CheckImage(irradiance, "irradiance", 1));
    } else {
      return absl::InvalidArgumentError("irradiance: must be a floating-point [N, 1, H, W] tensor");
    }
    return QuantizeIrradianceOfValid(irradiance);
  });
}

absl::StatusOr<torch::Tensor> FillSky(const torch::Tensor& basecolor, const torch::Tensor& depth,
                                      const torch::Tensor& sky) {
  return TorchCall("FillSky", [&]() -> absl::StatusOr<torch::Tensor> {
    FD_RETURN_IF_ERROR(CheckImage(basecolor, "basecolor", 3));
    FD_RETURN_IF_ERROR(CheckInput(depth, "depth", 1, basecolor, "basecolor"));
    FD_RETURN_IF_ERROR(CheckInput(sky, "sky image", 3, basecolor, "basecolor"));
    return FillSkyOfValid(AsUint8(basecolor), AsUint8(depth), AsUint8(sky));
  });
}

absl::StatusOr<torch::Tensor> PackCondition(const GBuffer& gbuffer,
                                            const torch::Tensor& irradiance_u8,
                                            int64_t size_multiple) {
  return TorchCall("PackCondition", [&]() -> absl::StatusOr<torch::Tensor> {
    FD_RETURN_IF_ERROR(CheckGBuffer(gbuffer, size_multiple));
    if (!irradiance_u8.defined() || irradiance_u8.scalar_type() != torch::kUInt8) {
      return absl::InvalidArgumentError("irradiance: must be a uint8 [N, 1, H, W] tensor");
    }
    FD_RETURN_IF_ERROR(CheckInput(irradiance_u8, "irradiance", 1, gbuffer.basecolor, "basecolor"));
    return PackOfValid(gbuffer, AsUint8(gbuffer.basecolor), irradiance_u8);
  });
}

absl::StatusOr<FrameCondition> BuildFrameCondition(const FrameConditionInputs& in) {
  return TorchCall("BuildFrameCondition", [&]() -> absl::StatusOr<FrameCondition> {
    const GBuffer& g = in.gbuffer;
    FD_RETURN_IF_ERROR(CheckGBuffer(g, in.size_multiple));
    const bool has_prev_output = in.previous_output.defined();
    if (has_prev_output != in.previous_basecolor.defined()) {
      return absl::InvalidArgumentError(
          "previous_output and previous_basecolor must be given together (irradiance source) or "
          "both left out (black irradiance)");
    }
    if (has_prev_output) {
      FD_RETURN_IF_ERROR(
          CheckInput(in.previous_output, "previous_output", 3, g.basecolor, "basecolor"));
      FD_RETURN_IF_ERROR(
          CheckInput(in.previous_basecolor, "previous_basecolor", 3, g.basecolor, "basecolor"));
    }
    torch::Tensor sky;
    switch (in.sky_fill) {
      case SkyFillMode::kSkyImage:
        if (!in.sky_image.defined()) {
          return absl::InvalidArgumentError("sky_image: required by sky fill mode 'sky image'");
        }
        FD_RETURN_IF_ERROR(CheckInput(in.sky_image, "sky_image", 3, g.basecolor, "basecolor"));
        sky = in.sky_image;
        break;
      case SkyFillMode::kPreviousOutput:
        if (!has_prev_output) {
          return absl::InvalidArgumentError(
              "previous_output: required by sky fill mode 'previous output' (there is no "
              "previous frame yet; use another mode for the first frame)");
        }
        sky = in.previous_output;
        break;
      case SkyFillMode::kNone:
        break;
    }

    FrameCondition out;
    const torch::Tensor basecolor = AsUint8(g.basecolor);
    out.basecolor =
        sky.defined() ? FillSkyOfValid(basecolor, AsUint8(g.depth), AsUint8(sky)) : basecolor;
    if (has_prev_output && !in.black_irradiance) {
      out.irradiance =
          IrradianceOfValid(AsUint8(in.previous_output), AsUint8(in.previous_basecolor));
    } else {
      out.irradiance = torch::zeros({basecolor.size(0), 1, basecolor.size(2), basecolor.size(3)},
                                    torch::dtype(torch::kFloat32).device(basecolor.device()));
    }
    out.irradiance_u8 = QuantizeIrradianceOfValid(out.irradiance);
    out.condition = PackOfValid(g, out.basecolor, out.irradiance_u8);
    return out;
  });
}

absl::StatusOr<torch::Tensor> BasecolorPatches(const torch::Tensor& condition, int64_t factor) {
  if (factor < 1) return absl::InvalidArgumentError("basecolor patches: factor must be >= 1");
  if (!condition.defined() || condition.dim() != 4 || condition.size(1) < 3 ||
      condition.size(2) % factor != 0 || condition.size(3) % factor != 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("basecolor patches: condition must be [N, >= 3, H, W] with H and W "
                     "multiples of ",
                     factor));
  }
  return TorchCall("BasecolorPatches", [&]() -> absl::StatusOr<torch::Tensor> {
    // [N, 3, H, W] -> [N, 3 * f * f, H / f, W / f] (torch.nn.PixelUnshuffle).
    return torch::pixel_unshuffle(condition.slice(1, 0, 3), factor).contiguous();
  });
}

}  // namespace fd::model

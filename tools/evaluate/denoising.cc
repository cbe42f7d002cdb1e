#include "tools/evaluate/denoising.h"

#include <torch/torch.h>

#include <algorithm>
#include <cstring>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "base/status_macros.h"
#include "client_sdk/dataset.h"
#include "client_sdk/image.h"
#include "client_sdk/image_io.h"
#include "client_sdk/metrics.h"
#include "model/pipeline/environment.h"
#include "model/pipeline/frame_pipeline.h"
#include "model/runtime/torch_call.h"
#include "tools/evaluate/image_helpers.h"

namespace fd::evaluate {
namespace {

using fd::client::Image8;
using fd::client::ImageF;

// A dataset buffer as the uint8 [H, W, C] tensor a PipelineInput takes.
torch::Tensor ToTensor(const fd::client::AnyImage& image) {
  Image8 bytes = fd::client::ToUint8(image);
  return torch::from_blob(bytes.pixels.data(), {bytes.height, bytes.width, bytes.channels},
                          torch::kUInt8)
      .clone();
}

struct Sums {
  double noise_mse = 0, psnr_roundtrip = 0, psnr_gt = 0;
};

}  // namespace

absl::StatusOr<std::string> DescribeDenoising(const DenoisingOptions& o) {
  fd::model::EnvironmentOptions env_options;
  env_options.lora_policy = fd::model::LoraPolicy::kIfPresent;
  FD_ASSIGN_OR_RETURN(std::shared_ptr<fd::model::Environment> env,
                      fd::model::LoadEnvironment(o.env_dir, env_options));
  fd::client::DatasetOptions dataset_options;
  dataset_options.require_final_image = true;
  FD_ASSIGN_OR_RETURN(fd::client::Dataset dataset,
                      fd::client::Dataset::Open(o.sequence, dataset_options));
  const int64_t n = static_cast<int64_t>(dataset.frames().size());
  if (n < 2)
    return absl::InvalidArgumentError(absl::StrCat(o.sequence, " has fewer than 2 frames"));
  FD_ASSIGN_OR_RETURN(const fd::model::Scheduler* scheduler,
                      env->GetScheduler(env->settings.scheduler));
  const torch::Tensor alphas_cumprod = scheduler->alphas_cumprod();
  const std::string& prediction_type = scheduler->settings().prediction_type;
  for (int t : o.timesteps) {
    if (t < 0 || t >= alphas_cumprod.size(0)) {
      return absl::InvalidArgumentError(
          absl::StrCat("timestep ", t, " is outside [0, ", alphas_cumprod.size(0), ")"));
    }
  }
  const int frames = static_cast<int>(std::clamp<int64_t>(o.frames, 1, n - 1));
  fd::model::FramePipeline pipeline(env);
  std::vector<Sums> sums(o.timesteps.size());
  const int columns = 1 + static_cast<int>(o.timesteps.size());
  Image8 sheet;
  for (int f = 0; f < frames; ++f) {
    const size_t position = static_cast<size_t>(1 + f * (n - 1) / frames);
    FD_ASSIGN_OR_RETURN(fd::client::DatasetFrame frame, dataset.ReadFrame(position));
    FD_ASSIGN_OR_RETURN(fd::client::DatasetFrame previous, dataset.ReadFrame(position - 1));
    // The request of teacher-forced validation (trainer/validation.cc): the
    // ground-truth previous frame and the ground-truth sky.
    fd::model::PipelineInput request;
    request.previous_frame = ToTensor(*previous.final_image);
    request.previous_basecolor = ToTensor(previous.basecolor);
    request.basecolor = ToTensor(frame.basecolor);
    request.normals = ToTensor(frame.normals);
    request.depth = ToTensor(frame.depth);
    request.roughness = ToTensor(frame.roughness);
    if (frame.metallic) request.metallic = ToTensor(*frame.metallic);
    request.sky_mode = fd::model::SkyFillMode::kSkyImage;
    request.keep_intermediates = true;  // the condition is read below
    request.sky_image = ToTensor(*frame.final_image);
    request.vae_noise_seed = o.seed;
    request.init_noise_seed = o.seed + 1;
    FD_ASSIGN_OR_RETURN(std::vector<fd::model::FrameState> states,
                        pipeline.Begin(absl::MakeConstSpan(&request, 1)));
    const fd::model::FrameState& state = states[0];
    const Image8 gt = fd::client::ToUint8(*frame.final_image);
    absl::Status status = fd::model::TorchCall("denoising", [&]() -> absl::Status {
      torch::InferenceMode inference;
      const double sf = env->vae->config().scaling_factor;
      const torch::Tensor x = ToTensor(*frame.final_image)
                                      .permute({2, 0, 1})
                                      .unsqueeze(0)
                                      .to(env->device, torch::kFloat32) /
                                  127.5 -
                              1.0;
      FD_ASSIGN_OR_RETURN(fd::model::LatentPosterior posterior, env->vae->Encode(x));
      const torch::Tensor z0 = posterior.mean.to(torch::kFloat32) * sf;
      FD_ASSIGN_OR_RETURN(torch::Tensor roundtrip_decoded, env->vae->Decode(z0 / sf));
      const Image8 roundtrip = DecodedToImages(roundtrip_decoded.to(torch::kFloat32).cpu())[0];
      if (sheet.empty()) sheet = Image8(columns * gt.width, frames * gt.height, 3);
      auto paste = [&](const Image8& image, int column) {
        Blit(image, &sheet, column * image.width, f * image.height);
      };
      paste(roundtrip, 0);
      for (size_t k = 0; k < o.timesteps.size(); ++k) {
        const int t = o.timesteps[k];
        torch::Generator gen = at::make_generator<at::CPUGeneratorImpl>(
            o.seed * 1000003ULL + static_cast<uint64_t>(position) * 1009ULL + t);
        const torch::Tensor noise = torch::randn(z0.sizes(), gen).to(env->device);
        const double a = alphas_cumprod[t].item<double>();
        const torch::Tensor xt = std::sqrt(a) * z0 + std::sqrt(1 - a) * noise;
        const torch::Tensor timestep = torch::full({1}, t, torch::kLong).to(env->device);
        FD_ASSIGN_OR_RETURN(std::vector<torch::Tensor> residuals,
                            env->controlnet->Run(xt, timestep, state.prompt_embeds, state.condition,
                                                 env->settings.conditioning_scale));
        FD_ASSIGN_OR_RETURN(torch::Tensor output,
                            env->unet->Run(torch::cat({xt, state.prev_latent}, 1), timestep,
                                           state.prompt_embeds, residuals));
        output = output.to(torch::kFloat32);
        // The noise and clean-latent estimates, as the schedulers convert
        // the model output by the config's prediction_type.
        torch::Tensor eps;
        torch::Tensor x0;
        if (prediction_type == "v_prediction") {
          x0 = std::sqrt(a) * xt - std::sqrt(1 - a) * output;
          eps = std::sqrt(a) * output + std::sqrt(1 - a) * xt;
        } else if (prediction_type == "sample") {
          x0 = output;
          eps = (xt - std::sqrt(a) * x0) / std::sqrt(1 - a);
        } else {
          eps = output;
          x0 = (xt - std::sqrt(1 - a) * eps) / std::sqrt(a);
        }
        FD_ASSIGN_OR_RETURN(torch::Tensor decoded, env->vae->Decode(x0 / sf));
        const Image8 image = DecodedToImages(decoded.to(torch::kFloat32).cpu())[0];
        paste(image, 1 + static_cast<int>(k));
        FD_ASSIGN_OR_RETURN(double psnr_roundtrip,
                            fd::client::Psnr(ToUnitFloat(image), ToUnitFloat(roundtrip)));
        FD_ASSIGN_OR_RETURN(double psnr_gt, fd::client::Psnr(ToUnitFloat(image), ToUnitFloat(gt)));
        sums[k].noise_mse += torch::mse_loss(eps, noise).item<double>();
        sums[k].psnr_roundtrip += std::min(psnr_roundtrip, 100.0);
        sums[k].psnr_gt += std::min(psnr_gt, 100.0);
      }
      return absl::OkStatus();
    });
    FD_RETURN_IF_ERROR(status);
  }
  if (!o.sheet.empty()) FD_RETURN_IF_ERROR(fd::client::WritePng(o.sheet, sheet));
  std::string out =
      absl::StrFormat("%d frames of %s, teacher-forced (ground-truth previous frame and sky)\n",
                      frames, o.sequence);
  for (size_t k = 0; k < o.timesteps.size(); ++k) {
    absl::StrAppend(&out,
                    absl::StrFormat("t=%3d  noise MSE %.4f  x0 PSNR vs round trip %5.2f dB"
                                    "  vs ground truth %5.2f dB\n",
                                    o.timesteps[k], sums[k].noise_mse / frames,
                                    sums[k].psnr_roundtrip / frames, sums[k].psnr_gt / frames));
  }
  return out;
}

}  // namespace fd::evaluate

// Autoregressive validation renders; see validation.h.
#include "trainer/validation.h"

#include <torch/torch.h>

#include <algorithm>

#include "absl/strings/str_cat.h"
#include "client_sdk/metrics.h"
#include "model/pipeline/frame_pipeline.h"

namespace fd::trainer {
namespace {

// uint8 [C, H, W] -> HWC tensor (what PipelineInput takes).
torch::Tensor Hwc(const torch::Tensor& chw) { return chw.permute({1, 2, 0}).contiguous(); }

// Copies an HWC uint8 tensor (1 or 3 channels) into `sheet` at (x0, y0).
void Paste(const torch::Tensor& hwc_u8, int x0, int y0, fd::client::Image8& sheet) {
  const torch::Tensor c = hwc_u8.contiguous();
  const int h = static_cast<int>(c.size(0)), w = static_cast<int>(c.size(1));
  const int channels = static_cast<int>(c.size(2));
  const uint8_t* src = c.data_ptr<uint8_t>();
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      for (int k = 0; k < 3; ++k) {
        sheet.at(x0 + x, y0 + y, k) =
            src[(size_t(y) * w + x) * channels + std::min(k, channels - 1)];
      }
    }
  }
}

}  // namespace

fd::client::ImageF ToImageF(const torch::Tensor& hwc_u8) {
  const torch::Tensor c = hwc_u8.contiguous();
  fd::client::ImageF image(static_cast<int>(c.size(1)), static_cast<int>(c.size(0)),
                           static_cast<int>(c.size(2)));
  const uint8_t* src = c.data_ptr<uint8_t>();
  for (size_t i = 0; i < image.pixels.size(); ++i) image.pixels[i] = src[i] / 255.0f;
  return image;
}

fd::model::PipelineInput MakeFrameRequest(const FrameRequestInputs& in) {
  const TrainingSequence& seq = *in.seq;
  fd::model::PipelineInput request;
  request.previous_frame = Hwc(in.previous);
  request.previous_basecolor = Hwc(seq.basecolor[in.previous_position]);
  request.basecolor = Hwc(seq.basecolor[in.position]);
  request.normals = Hwc(seq.normals[in.position]);
  request.depth = Hwc(seq.depth[in.position]);
  request.roughness = Hwc(seq.roughness[in.position]);
  request.metallic = Hwc(seq.metallic[in.position]);
  request.sky_mode = fd::model::SkyFillMode::kSkyImage;
  request.sky_image = Hwc(seq.final_image[in.position]);
  request.vae_noise_seed = 2 * in.seed;
  request.init_noise_seed = 2 * in.seed + 1;
  return request;
}

absl::StatusOr<ValidationResult> RenderValidation(
    const std::shared_ptr<const fd::model::Environment>& environment, const TrainingSequence& seq,
    int frames) {
  if (seq.size() < 2) {
    return absl::InvalidArgumentError(
        absl::StrCat("validation sequence ", seq.dir, " needs at least 2 frames"));
  }
  if (frames < 1) return absl::InvalidArgumentError("validation frames must be >= 1");
  const int64_t count = std::min<int64_t>(frames, seq.size() - 1);
  fd::model::FramePipeline pipeline(environment);
  ValidationResult result;
  std::vector<torch::Tensor> irradiance;
  torch::Tensor previous = seq.final_image[0];  // the keyframe
  for (int64_t p = 1; p <= count; ++p) {
    FrameRequestInputs in{&seq, p, previous, p - 1, static_cast<uint64_t>(p)};
    fd::model::PipelineInput request = MakeFrameRequest(in);
    request.keep_intermediates = true;  // the contact sheet shows the irradiance
    absl::StatusOr<std::vector<fd::model::FrameState>> states =
        pipeline.Begin(absl::MakeConstSpan(&request, 1));
    if (!states.ok()) return states.status();
    fd::model::FrameState* state = &(*states)[0];
    while (!state->finished()) {
      if (absl::Status s = pipeline.Step(absl::MakeConstSpan(&state, 1)); !s.ok()) return s;
    }
    irradiance.push_back(state->irradiance_u8[0].permute({1, 2, 0}).contiguous());
    absl::StatusOr<std::vector<fd::model::FrameOutput>> out =
        pipeline.Finish(absl::MakeConstSpan(&state, 1));
    if (!out.ok()) return out.status();
    const torch::Tensor image = (*out)[0].image_uint8;  // [H, W, 3]
    absl::StatusOr<double> psnr =
        fd::client::Psnr(ToImageF(image), ToImageF(Hwc(seq.final_image[p])));
    if (!psnr.ok()) return psnr.status();
    absl::StatusOr<double> ssim =
        fd::client::Ssim(ToImageF(image), ToImageF(Hwc(seq.final_image[p])));
    const double ssim_value = ssim.ok() ? *ssim : 0.0;  // images under 11x11 have no SSIM
    result.frames.push_back({seq.frame_numbers[static_cast<size_t>(p)], *psnr, ssim_value});
    result.rendered.push_back(image);
    previous = image.permute({2, 0, 1}).contiguous();
  }
  for (const ValidationFrame& f : result.frames) {
    result.mean_psnr += std::min(f.psnr, 100.0) / static_cast<double>(result.frames.size());
    result.mean_ssim += f.ssim / static_cast<double>(result.frames.size());
  }
  // Up to 4 rows, evenly spread over the rendered frames.
  const int rows = static_cast<int>(std::min<int64_t>(4, count));
  const int h = static_cast<int>(seq.final_image.size(2)),
            w = static_cast<int>(seq.final_image.size(3));
  result.contact_sheet = fd::client::Image8(4 * w, rows * h, 3);
  for (int r = 0; r < rows; ++r) {
    const int64_t i = rows == 1 ? 0 : r * (count - 1) / (rows - 1);
    const int64_t p = i + 1;
    Paste(Hwc(seq.final_image[p]), 0, r * h, result.contact_sheet);
    Paste(result.rendered[static_cast<size_t>(i)], w, r * h, result.contact_sheet);
    Paste(Hwc(seq.basecolor[p]), 2 * w, r * h, result.contact_sheet);
    Paste(irradiance[static_cast<size_t>(i)], 3 * w, r * h, result.contact_sheet);
  }
  return result;
}

}  // namespace fd::trainer

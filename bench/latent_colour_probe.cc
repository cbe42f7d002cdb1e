// fd_latent_colour_probe: how much an autoencoder's latent moves when a
// frame's colours change, against when its content changes, and whether a
// latent cell tells its pixel block's colour linearly. The diffusion stages
// regress on latents, so a change that moves the latent little costs the
// denoiser little loss however large it is in pixels. Not a test: nothing is
// asserted.
//
//   fd_latent_colour_probe --vae ENV_OR_VAE_DIR --data SEQUENCE_DIR...
//                          [--resolution 128x128] [--frames 16]
//
// For `--frames` frames spread over the sequences, each frame x is compared
// with:
//   * x recoloured (trainer RecolourFrame, each of RGB's five other orders:
//     the albedo's channels reordered and the frame relit to match);
//   * x reduced to its grey (the channel mean: no hue, same light and dark);
//   * the next frame of its sequence (the camera moved one frame: content).
// For each: the pixel MSE (images in [-1, 1]), the latent MSE (posterior
// means times the scaling factor, what the denoiser regresses on) and their
// ratio, averaged over the frames. Then the mean posterior variance (the
// noise latent_dist.sample() adds to every training latent), and the R^2 of
// least-squares fits from a latent cell (and a bias) to the mean colour of
// its pixel block, and to the block's chroma (colour minus its channel mean):
// a latent-space colour loss would need the colour to be linear there.
//
// Results and the command that produced them: docs/EVALUATION.md ("Why the
// colours are not learnt").
#include <torch/torch.h>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <string>
#include <vector>

#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"
#include "model/networks/vae.h"
#include "trainer/sample_builder.h"
#include "trainer/training_data.h"

namespace {

namespace fs = std::filesystem;
using fd::trainer::ToSigned;

struct Sum {
  double pixel = 0, latent = 0;
  int count = 0;
  void Add(double p, double l) {
    pixel += p;
    latent += l;
    ++count;
  }
};

// R^2 of the least-squares fit of `targets` [N, K, H, W], averaged over the
// latent grid's blocks, from `latents` [N, C, h, w] and a bias.
double BlockFitR2(const torch::Tensor& latents, const torch::Tensor& targets) {
  const int64_t channels = latents.size(1);
  const torch::Tensor blocks = torch::avg_pool2d(targets, targets.size(2) / latents.size(2))
                                   .permute({0, 2, 3, 1})
                                   .reshape({-1, targets.size(1)})
                                   .to(torch::kFloat64);
  const torch::Tensor z = latents.permute({0, 2, 3, 1}).reshape({-1, channels}).to(torch::kFloat64);
  const torch::Tensor design = torch::cat({z, torch::ones({z.size(0), 1}, z.options())}, 1);
  const torch::Tensor solution =
      torch::linalg::solve(design.t().mm(design), design.t().mm(blocks), /*left=*/true);
  const double residual = (blocks - design.mm(solution)).pow(2).sum().item<double>();
  const double total = (blocks - blocks.mean(0, true)).pow(2).sum().item<double>();
  return total > 0 ? 1.0 - residual / total : 0.0;
}

int Usage(const char* why) {
  std::fprintf(stderr,
               "fd_latent_colour_probe: %s\nusage: fd_latent_colour_probe --vae DIR --data DIR... "
               "[--resolution WxH] [--frames N]\n",
               why);
  return 2;
}

}  // namespace

int main(int argc, char** argv) {
  std::string vae_dir;
  std::vector<std::string> data_dirs;
  int width = 128, height = 128, frames = 16;
  for (int i = 1; i < argc; ++i) {
    const std::string flag = argv[i];
    if (i + 1 >= argc) return Usage(("missing value for " + flag).c_str());
    const std::string value = argv[++i];
    if (flag == "--vae") {
      vae_dir = value;
    } else if (flag == "--data") {
      data_dirs.push_back(value);
    } else if (flag == "--frames") {
      if (!absl::SimpleAtoi(value, &frames) || frames < 1) return Usage("bad --frames");
    } else if (flag == "--resolution") {
      std::vector<std::string> parts = absl::StrSplit(value, 'x');
      if (parts.size() != 2 || !absl::SimpleAtoi(parts[0], &width) ||
          !absl::SimpleAtoi(parts[1], &height)) {
        return Usage("bad --resolution (WxH)");
      }
    } else {
      return Usage(("unknown flag " + flag).c_str());
    }
  }
  if (vae_dir.empty() || data_dirs.empty()) return Usage("--vae and --data are required");
  if (fs::exists(fs::path(vae_dir) / "vae")) vae_dir = (fs::path(vae_dir) / "vae").string();
  torch::set_num_threads(1);

  fd::trainer::TrainingDataOptions data_options;
  data_options.width = width;
  data_options.height = height;
  absl::StatusOr<fd::trainer::TrainingData> data =
      fd::trainer::LoadTrainingData(data_dirs, data_options);
  if (!data.ok()) return Usage(std::string(data.status().message()).c_str());
  absl::StatusOr<fd::model::AutoencoderKL> vae =
      fd::model::LoadVae(vae_dir, torch::kCPU, torch::kFloat32);
  if (!vae.ok()) return Usage(std::string(vae.status().message()).c_str());

  torch::NoGradGuard no_grad;
  const double scale = (*vae)->config().scaling_factor;
  Sum recoloured[fd::trainer::kChannelOrderCount], grey, next;
  std::vector<torch::Tensor> all_latents, all_images;
  double posterior_variance = 0;
  const int64_t total = data->frame_count();
  for (int k = 0; k < frames; ++k) {
    int64_t flat = (total - 1) * k / std::max(frames - 1, 1);
    size_t s = 0;
    while (flat >= data->sequences[s].size()) flat -= data->sequences[s++].size();
    const fd::trainer::TrainingSequence& seq = data->sequences[s];
    const int64_t p = std::min(flat, seq.size() - 2);  // one with a next frame
    const torch::Tensor x = seq.final_image[p];
    fd::model::LatentPosterior posterior = (*vae)->encode(ToSigned(x).unsqueeze(0));
    const torch::Tensor latent = posterior.mean * scale;
    posterior_variance += (posterior.std * scale).pow(2).mean().item<double>();
    all_latents.push_back(latent);
    all_images.push_back(ToSigned(x).unsqueeze(0));
    auto compare = [&](const torch::Tensor& other, Sum& sum) {
      const torch::Tensor other_latent = (*vae)->encode(ToSigned(other).unsqueeze(0)).mean * scale;
      sum.Add((ToSigned(other) - ToSigned(x)).pow(2).mean().item<double>(),
              (other_latent - latent).pow(2).mean().item<double>());
    };
    for (int order = 1; order < fd::trainer::kChannelOrderCount; ++order) {
      compare(fd::trainer::RecolourFrame(x, seq.basecolor[p], seq.depth[p], order),
              recoloured[order]);
    }
    compare(x.to(torch::kFloat32).mean(0, true).round().to(torch::kUInt8).expand({3, -1, -1}),
            grey);
    compare(seq.final_image[p + 1], next);
  }

  std::printf("%d frames of %lld, %dx%d, VAE %s\n\n", frames, static_cast<long long>(total), width,
              height, vae_dir.c_str());
  std::printf("| change | pixel MSE | latent MSE | latent / pixel |\n|---|---:|---:|---:|\n");
  auto row = [](const std::string& name, const Sum& sum) {
    std::printf("| %s | %.5f | %.5f | %.3f |\n", name.c_str(), sum.pixel / sum.count,
                sum.latent / sum.count, sum.latent / sum.pixel);
  };
  for (int order = 1; order < fd::trainer::kChannelOrderCount; ++order) {
    const auto& o = fd::trainer::kChannelOrders[static_cast<size_t>(order)];
    row("recoloured, albedo channels " + std::string(1, "RGB"[o[0]]) + "RGB"[o[1]] + "RGB"[o[2]],
        recoloured[order]);
  }
  row("grey (channel mean)", grey);
  row("next frame", next);
  const torch::Tensor latents = torch::cat(all_latents), images = torch::cat(all_images);
  std::printf("\nposterior variance (latent_dist.sample()'s noise): %.5f per element\n",
              posterior_variance / frames);
  std::printf("R^2 of a latent cell's linear fit to its block's mean colour: %.3f, chroma: %.3f\n",
              BlockFitR2(latents, images), BlockFitR2(latents, images - images.mean(1, true)));
  // Per channel, after the scaling factor: the diffusion stages noise every
  // channel alike, so a channel with a larger spread keeps its signal to
  // higher noise levels than the others.
  const torch::Tensor channel_mean = latents.mean({0, 2, 3});
  const torch::Tensor channel_std =
      (latents - channel_mean.view({1, -1, 1, 1})).pow(2).mean({0, 2, 3}).sqrt();
  std::printf("\n| latent channel | mean | std |\n|---:|---:|---:|\n");
  for (int64_t c = 0; c < latents.size(1); ++c) {
    std::printf("| %lld | %.3f | %.3f |\n", static_cast<long long>(c),
                channel_mean[c].item<double>(), channel_std[c].item<double>());
  }
  return 0;
}

#include "tools/evaluate/evaluation.h"

#include <torch/torch.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <numeric>
#include <set>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "base/status_macros.h"
#include "client_sdk/dataset.h"
#include "client_sdk/image.h"
#include "client_sdk/image_io.h"
#include "client_sdk/irradiance.h"
#include "client_sdk/metrics.h"
#include "client_sdk/plot.h"
#include "client_sdk/raster.h"
#include "model/networks/vae.h"
#include "model/runtime/torch_call.h"
#include "nlohmann/json.hpp"
#include "tools/evaluate/image_helpers.h"

namespace fd::evaluate {
namespace {

namespace fs = std::filesystem;
using Json = nlohmann::json;
using fd::client::Image8;
using fd::client::ImageF;

absl::StatusOr<Image8> ReadRgb8(const std::string& path) {
  absl::StatusOr<fd::client::AnyImage> image = fd::client::ReadImage(path);
  if (!image.ok()) return image.status();
  return fd::client::ToUint8(fd::client::ToChannels(*image, 3));
}

double Mean(const std::vector<double>& v, size_t begin, size_t end) {
  end = std::min(end, v.size());
  if (begin >= end) return std::nan("");
  return std::accumulate(v.begin() + static_cast<std::ptrdiff_t>(begin),
                         v.begin() + static_cast<std::ptrdiff_t>(end), 0.0) /
         static_cast<double>(end - begin);
}

// Mean absolute per-pixel change from the previous frame, in [0, 1].
double MeanAbsChange(const Image8& now, const Image8& before) {
  double sum = 0;
  for (size_t i = 0; i < now.pixels.size(); ++i) {
    sum += std::abs(static_cast<int>(now.pixels[i]) - static_cast<int>(before.pixels[i]));
  }
  return sum / (255.0 * static_cast<double>(now.pixels.size()));
}

// Mean absolute difference between the two sequences' frame-to-frame
// changes: 0 when the prediction changes exactly as the ground truth does;
// flicker (changes the ground truth does not have) raises it.
double ChangeError(const Image8& now, const Image8& before, const Image8& gt_now,
                   const Image8& gt_before) {
  double sum = 0;
  for (size_t i = 0; i < now.pixels.size(); ++i) {
    const int change = static_cast<int>(now.pixels[i]) - static_cast<int>(before.pixels[i]);
    const int gt_change =
        static_cast<int>(gt_now.pixels[i]) - static_cast<int>(gt_before.pixels[i]);
    sum += std::abs(change - gt_change);
  }
  return sum / (255.0 * static_cast<double>(now.pixels.size()));
}

// The mean of every kBlock x kBlock block (a partial block at the right or
// bottom edge is averaged over the pixels it has).
constexpr int kBlock = 8;  // SD's VAE downsampling: one latent pixel
ImageF BlockMeans(const ImageF& image) {
  const int bw = (image.width + kBlock - 1) / kBlock, bh = (image.height + kBlock - 1) / kBlock;
  ImageF out(bw, bh, image.channels);
  std::vector<int> count(static_cast<size_t>(bw) * bh, 0);
  for (int y = 0; y < image.height; ++y) {
    for (int x = 0; x < image.width; ++x) {
      ++count[static_cast<size_t>(y / kBlock) * bw + x / kBlock];
      for (int c = 0; c < image.channels; ++c) {
        out.at(x / kBlock, y / kBlock, c) += image.at(x, y, c);
      }
    }
  }
  for (int y = 0; y < bh; ++y) {
    for (int x = 0; x < bw; ++x) {
      for (int c = 0; c < image.channels; ++c) {
        out.at(x, y, c) /= static_cast<float>(count[static_cast<size_t>(y) * bw + x]);
      }
    }
  }
  return out;
}

struct Series {
  std::vector<double> psnr;
  std::vector<double> ssim;
  // PSNR of the 8x8 block means: the error left at the latent's own grid
  // (brightness and colour per block), with the texture inside blocks
  // taken out.
  std::vector<double> block_psnr;

  // Appends PSNR and SSIM of `a` against `b`.
  absl::Status Add(const ImageF& a, const ImageF& b) {
    absl::StatusOr<double> p = fd::client::Psnr(a, b);
    if (!p.ok()) return p.status();
    absl::StatusOr<double> s = fd::client::Ssim(a, b);
    if (!s.ok()) return s.status();
    absl::StatusOr<double> block = fd::client::Psnr(BlockMeans(a), BlockMeans(b));
    if (!block.ok()) return block.status();
    psnr.push_back(*p);
    ssim.push_back(*s);
    block_psnr.push_back(*block);
    return absl::OkStatus();
  }
};

Json Summarize(const Series& s, int window) {
  const size_t n = s.psnr.size();
  Json j = {{"mean_psnr", Mean(s.psnr, 0, n)},
            {"mean_ssim", Mean(s.ssim, 0, n)},
            {"mean_block8_psnr", Mean(s.block_psnr, 0, n)},
            {"psnr", s.psnr},
            {"ssim", s.ssim}};
  if (n >= 2 * static_cast<size_t>(window)) {
    j["first_window_mean_psnr"] = Mean(s.psnr, 0, window);
    j["last_window_mean_psnr"] = Mean(s.psnr, n - window, n);
    j["first_window_mean_ssim"] = Mean(s.ssim, 0, window);
    j["last_window_mean_ssim"] = Mean(s.ssim, n - window, n);
  }
  return j;
}

absl::Status WriteText(const fs::path& path, const std::string& text) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out << text;
  out.close();
  if (!out) return absl::InternalError(absl::StrCat("cannot write ", path.string()));
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<int64_t> WriteRoundTrip(const std::string& env_dir, const std::string& sequence,
                                       const std::string& out_dir, int threads) {
  torch::set_num_threads(std::max(1, threads));
  absl::StatusOr<fd::model::AutoencoderKL> vae =
      fd::model::LoadVae((fs::path(env_dir) / "vae").string(), torch::kCPU, torch::kFloat32);
  if (!vae.ok()) return vae.status();
  absl::StatusOr<std::map<int64_t, std::string>> frames = fd::client::ListFrameImages(sequence);
  if (!frames.ok()) return frames.status();
  std::error_code ec;
  fs::create_directories(out_dir, ec);
  if (ec) return absl::InternalError(absl::StrCat("cannot create ", out_dir, ": ", ec.message()));
  std::vector<std::pair<int64_t, std::string>> todo(frames->begin(), frames->end());
  constexpr size_t kBatch = 8;
  for (size_t start = 0; start < todo.size(); start += kBatch) {
    const size_t end = std::min(todo.size(), start + kBatch);
    std::vector<Image8> images;
    for (size_t i = start; i < end; ++i) {
      absl::StatusOr<Image8> image = ReadRgb8(todo[i].second);
      if (!image.ok()) return image.status();
      if (!images.empty() &&
          (image->width != images[0].width || image->height != images[0].height)) {
        return absl::InvalidArgumentError(
            absl::StrCat(todo[i].second, " differs in size from the frames before it"));
      }
      images.push_back(*std::move(image));
    }
    const int w = images[0].width, h = images[0].height;
    absl::StatusOr<std::vector<Image8>> decoded =
        fd::model::TorchCall("round trip", [&]() -> absl::StatusOr<std::vector<Image8>> {
          torch::NoGradGuard no_grad;
          std::vector<torch::Tensor> batch;
          for (Image8& image : images) {
            batch.push_back(torch::from_blob(image.pixels.data(), {h, w, 3}, torch::kUInt8)
                                .permute({2, 0, 1})
                                .to(torch::kFloat32));
          }
          // VaeImageProcessor.preprocess: [0, 255] -> [-1, 1].
          const torch::Tensor x = torch::stack(batch) / 127.5 - 1.0;
          const torch::Tensor y = (*vae)->decode((*vae)->encode(x).mean);
          return DecodedToImages(y);
        });
    if (!decoded.ok()) return decoded.status();
    for (size_t i = start; i < end; ++i) {
      const std::string path =
          (fs::path(out_dir) / absl::StrFormat("RoundTrip_%04d.png", todo[i].first)).string();
      if (absl::Status s = fd::client::WritePng(path, (*decoded)[i - start]); !s.ok()) return s;
    }
  }
  return static_cast<int64_t>(todo.size());
}

absl::StatusOr<std::string> DescribeLatents(const std::string& env_dir, const std::string& sequence,
                                            int frames) {
  absl::StatusOr<fd::model::AutoencoderKL> vae =
      fd::model::LoadVae((fs::path(env_dir) / "vae").string(), torch::kCPU, torch::kFloat32);
  if (!vae.ok()) return vae.status();
  absl::StatusOr<std::map<int64_t, std::string>> listed = fd::client::ListFrameImages(sequence);
  if (!listed.ok()) return listed.status();
  std::vector<std::string> paths;
  for (const auto& [index, path] : *listed) paths.push_back(path);
  const size_t n = std::min(paths.size(), static_cast<size_t>(std::max(1, frames)));
  std::vector<Image8> images;
  for (size_t i = 0; i < n; ++i) {
    absl::StatusOr<Image8> image = ReadRgb8(paths[i * paths.size() / n]);
    if (!image.ok()) return image.status();
    if (!images.empty() && (image->width != images[0].width || image->height != images[0].height)) {
      return absl::InvalidArgumentError("the frames differ in size");
    }
    images.push_back(*std::move(image));
  }
  return fd::model::TorchCall("latent statistics", [&]() -> absl::StatusOr<std::string> {
    torch::NoGradGuard no_grad;
    std::vector<torch::Tensor> batch;
    for (Image8& image : images) {
      batch.push_back(
          torch::from_blob(image.pixels.data(), {image.height, image.width, 3}, torch::kUInt8)
              .permute({2, 0, 1})
              .to(torch::kFloat32));
    }
    const fd::model::LatentPosterior p = (*vae)->encode(torch::stack(batch) / 127.5 - 1.0);
    std::string out = absl::StrFormat("%d frames, scaling_factor %.4f\n", images.size(),
                                      (*vae)->config().scaling_factor);
    for (int64_t c = 0; c < p.mean.size(1); ++c) {
      absl::StrAppend(
          &out,
          absl::StrFormat("channel %2d  mean %+.3f  spread of mean %.3f  posterior std %.3f\n", c,
                          p.mean.select(1, c).mean().item<double>(),
                          p.mean.select(1, c).std().item<double>(),
                          p.std.select(1, c).mean().item<double>()));
    }
    return out;
  });
}

absl::Status WriteReport(const ReportOptions& options) {
  if (options.variants.empty()) return absl::InvalidArgumentError("no --variant given");
  absl::StatusOr<std::map<int64_t, std::string>> gt = fd::client::ListFrameImages(options.sequence);
  if (!gt.ok()) return gt.status();
  absl::StatusOr<std::map<int64_t, std::string>> basecolor =
      fd::client::ListFrameImages((fs::path(options.sequence) / "BaseColor").string());
  if (!basecolor.ok()) return basecolor.status();
  std::map<int64_t, std::string> roundtrip;
  if (!options.roundtrip.empty()) {
    absl::StatusOr<std::map<int64_t, std::string>> listed =
        fd::client::ListFrameImages(options.roundtrip);
    if (!listed.ok()) return listed.status();
    roundtrip = *std::move(listed);
  }
  std::vector<std::map<int64_t, std::string>> rendered;
  for (const Variant& v : options.variants) {
    absl::StatusOr<std::map<int64_t, std::string>> listed = fd::client::ListFrameImages(v.dir);
    if (!listed.ok()) {
      return absl::Status(listed.status().code(),
                          absl::StrCat(v.name, ": ", listed.status().message()));
    }
    rendered.push_back(*std::move(listed));
  }
  std::vector<int64_t> frames;
  for (const auto& [index, path] : rendered[0]) {
    bool everywhere = gt->count(index) && basecolor->count(index) &&
                      (roundtrip.empty() || roundtrip.count(index));
    for (const auto& r : rendered) everywhere = everywhere && r.count(index);
    if (everywhere) frames.push_back(index);
  }
  if (frames.empty()) {
    return absl::InvalidArgumentError("no frame is in the ground truth and every variant");
  }

  const size_t nv = options.variants.size();
  Series rt_vs_gt;
  std::vector<Series> vs_gt(nv), vs_rt(nv);
  std::vector<std::vector<double>> change(nv), change_error(nv);
  std::vector<double> gt_change;
  Image8 gt_before;
  std::vector<Image8> before(nv);
  // Contact sheet rows, evenly spaced over the frames (after the first, so
  // that the irradiance of the previous output exists).
  std::set<int64_t> sheet_frames;
  const int rows =
      std::max(1, std::min<int>(options.contact_rows, static_cast<int>(frames.size())));
  for (int r = 0; r < rows; ++r) {
    const size_t pos = frames.size() == 1 ? 0
                                          : 1 + static_cast<size_t>(r) * (frames.size() - 2) /
                                                    std::max(1, rows - 1);
    sheet_frames.insert(frames[std::min(pos, frames.size() - 1)]);
  }
  struct SheetRow {
    int64_t frame;
    Image8 gt, ours, basecolor, irradiance;
  };
  std::vector<SheetRow> sheet;
  Image8 basecolor_before;

  for (size_t f = 0; f < frames.size(); ++f) {
    const int64_t index = frames[f];
    absl::StatusOr<Image8> g = ReadRgb8(gt->at(index));
    if (!g.ok()) return g.status();
    absl::StatusOr<Image8> bc = ReadRgb8(basecolor->at(index));
    if (!bc.ok()) return bc.status();
    const ImageF gf = ToUnitFloat(*g);
    ImageF rf;
    if (!roundtrip.empty()) {
      absl::StatusOr<Image8> rt = ReadRgb8(roundtrip.at(index));
      if (!rt.ok()) return rt.status();
      rf = ToUnitFloat(*rt);
      if (absl::Status s = rt_vs_gt.Add(rf, gf); !s.ok()) return s;
    }
    const bool consecutive = f > 0 && frames[f - 1] == index - 1;
    if (consecutive) gt_change.push_back(MeanAbsChange(*g, gt_before));
    for (size_t v = 0; v < nv; ++v) {
      absl::StatusOr<Image8> pred = ReadRgb8(rendered[v].at(index));
      if (!pred.ok()) return pred.status();
      if (pred->width != g->width || pred->height != g->height) {
        return absl::InvalidArgumentError(
            absl::StrCat(options.variants[v].name, ": frame ", index, " is ", pred->width, "x",
                         pred->height, ", the ground truth ", g->width, "x", g->height));
      }
      const ImageF pf = ToUnitFloat(*pred);
      if (absl::Status s = vs_gt[v].Add(pf, gf); !s.ok()) return s;
      if (!roundtrip.empty()) {
        if (absl::Status s = vs_rt[v].Add(pf, rf); !s.ok()) return s;
      }
      if (consecutive) {
        change[v].push_back(MeanAbsChange(*pred, before[v]));
        change_error[v].push_back(ChangeError(*pred, before[v], *g, gt_before));
      }
      if (v == 0 && sheet_frames.count(index)) {
        SheetRow row{index, *g, *pred, *bc, {}};
        // What the model was given: the irradiance of its previous output
        // over the previous basecolor (absent for the first frame).
        if (consecutive) {
          absl::StatusOr<Image8> irr = fd::client::IrradianceMap(before[0], basecolor_before);
          if (irr.ok()) row.irradiance = *std::move(irr);
        }
        sheet.push_back(std::move(row));
      }
      before[v] = *std::move(pred);
    }
    gt_before = *std::move(g);
    basecolor_before = *std::move(bc);
  }

  std::error_code ec;
  fs::create_directories(options.out_dir, ec);
  if (ec) {
    return absl::InternalError(absl::StrCat("cannot create ", options.out_dir, ": ", ec.message()));
  }
  const fs::path out(options.out_dir);
  const size_t n = frames.size();

  Json variants = Json::array();
  for (size_t v = 0; v < nv; ++v) {
    Json j = {{"name", options.variants[v].name},
              {"dir", options.variants[v].dir},
              {"vs_ground_truth", Summarize(vs_gt[v], options.window)},
              {"frame_change", Mean(change[v], 0, change[v].size())},
              {"flicker_error", Mean(change_error[v], 0, change_error[v].size())}};
    if (!roundtrip.empty()) j["vs_roundtrip"] = Summarize(vs_rt[v], options.window);
    variants.push_back(j);
  }
  Json metrics = {{"sequence", options.sequence},
                  {"frames", frames},
                  {"window", options.window},
                  {"ground_truth_frame_change", Mean(gt_change, 0, gt_change.size())},
                  {"variants", variants}};
  if (!roundtrip.empty())
    metrics["roundtrip_vs_ground_truth"] = Summarize(rt_vs_gt, options.window);
  if (absl::Status s = WriteText(out / "metrics.json", metrics.dump(1) + "\n"); !s.ok()) return s;

  // per_frame.csv: one row per frame, PSNR / SSIM of every series.
  std::string csv = "frame";
  if (!roundtrip.empty()) csv += ",roundtrip_psnr,roundtrip_ssim";
  for (size_t v = 0; v < nv; ++v) {
    absl::StrAppend(&csv, ",v", v, "_psnr,v", v, "_ssim");
    if (!roundtrip.empty()) absl::StrAppend(&csv, ",v", v, "_psnr_vs_rt,v", v, "_ssim_vs_rt");
  }
  csv += "\n";
  for (size_t f = 0; f < n; ++f) {
    absl::StrAppend(&csv, frames[f]);
    if (!roundtrip.empty()) {
      absl::StrAppend(&csv, absl::StrFormat(",%.4f,%.5f", rt_vs_gt.psnr[f], rt_vs_gt.ssim[f]));
    }
    for (size_t v = 0; v < nv; ++v) {
      absl::StrAppend(&csv, absl::StrFormat(",%.4f,%.5f", vs_gt[v].psnr[f], vs_gt[v].ssim[f]));
      if (!roundtrip.empty()) {
        absl::StrAppend(&csv, absl::StrFormat(",%.4f,%.5f", vs_rt[v].psnr[f], vs_rt[v].ssim[f]));
      }
    }
    csv += "\n";
  }
  if (absl::Status s = WriteText(out / "per_frame.csv", csv); !s.ok()) return s;

  // results.md: the table docs/EVALUATION.md includes.
  const bool windows = n >= 2 * static_cast<size_t>(options.window);
  std::string md = absl::StrFormat(
      "%d frames (%d..%d), autoregressive from one ground-truth keyframe; uint8 frames.\n\n", n,
      frames.front(), frames.back());
  md += "| | PSNR ↑ | SSIM ↑ | PSNR vs AE ↑ | SSIM vs AE ↑ |";
  if (windows)
    absl::StrAppend(&md, " PSNR first ", options.window, " | PSNR last ", options.window, " |");
  md += " flicker error ↓ |\n|---|---:|---:|---:|---:|";
  if (windows) md += "---:|---:|";
  md += "---:|\n";
  auto fmt = [](double x, const char* f) {
    return std::isnan(x) ? std::string("–") : absl::StrFormat(f, x);
  };
  for (size_t v = 0; v < nv; ++v) {
    const Json& j = variants[v];
    absl::StrAppend(&md, "| ", options.variants[v].name, " | ",
                    fmt(j["vs_ground_truth"]["mean_psnr"], "%.2f"), " | ",
                    fmt(j["vs_ground_truth"]["mean_ssim"], "%.3f"), " | ");
    if (!roundtrip.empty()) {
      absl::StrAppend(&md, fmt(j["vs_roundtrip"]["mean_psnr"], "%.2f"), " | ",
                      fmt(j["vs_roundtrip"]["mean_ssim"], "%.3f"), " |");
    } else {
      md += "– | – |";
    }
    if (windows) {
      absl::StrAppend(&md, " ", fmt(j["vs_ground_truth"]["first_window_mean_psnr"], "%.2f"), " | ",
                      fmt(j["vs_ground_truth"]["last_window_mean_psnr"], "%.2f"), " |");
    }
    absl::StrAppend(&md, " ", fmt(j["flicker_error"], "%.4f"), " |\n");
  }
  if (!roundtrip.empty()) {
    const Json& r = metrics["roundtrip_vs_ground_truth"];
    absl::StrAppend(&md, "| Autoencoder round trip of the ground truth (ceiling) | ",
                    fmt(r["mean_psnr"], "%.2f"), " | ", fmt(r["mean_ssim"], "%.3f"), " | – | – |");
    if (windows) {
      absl::StrAppend(&md, " ", fmt(r["first_window_mean_psnr"], "%.2f"), " | ",
                      fmt(r["last_window_mean_psnr"], "%.2f"), " |");
    }
    md += " – |\n";
  }
  absl::StrAppend(&md,
                  "\nFlicker error: mean |Δprediction − Δground truth| per pixel between "
                  "consecutive frames, in [0, 1]; the ground truth's own mean |Δ| is ",
                  fmt(metrics["ground_truth_frame_change"], "%.4f"), ".\n");
  if (absl::Status s = WriteText(out / "results.md", md); !s.ok()) return s;

  // stability.png: ours against the frame index.
  std::vector<fd::client::PlotSeries> plot = {
      {absl::StrCat("PSNR (dB) vs ground truth: ", options.variants[0].name),
       vs_gt[0].psnr,
       {31, 119, 180}},
      {"SSIM vs ground truth", vs_gt[0].ssim, {214, 39, 40}}};
  if (!roundtrip.empty()) {
    plot.push_back({"PSNR (dB) vs the autoencoder round trip", vs_rt[0].psnr, {44, 160, 44}});
  }
  absl::StatusOr<Image8> chart = fd::client::PlotOverFrames(frames, plot, 960, 720);
  if (!chart.ok()) return chart.status();
  if (absl::Status s = fd::client::WritePng((out / "stability.png").string(), *chart); !s.ok()) {
    return s;
  }

  // contact_sheet.png: GT | ours | basecolor | irradiance, one row per frame.
  const int w = sheet.front().gt.width, h = sheet.front().gt.height;
  const int header = 20, margin = 4;
  Image8 sheet_image(4 * w + 5 * margin, header + static_cast<int>(sheet.size()) * (h + margin), 3);
  fd::client::Canvas canvas(&sheet_image);
  canvas.Fill({255, 255, 255});
  const char* titles[] = {"GROUND TRUTH", "OURS", "BASECOLOR", "IRRADIANCE"};
  for (int c = 0; c < 4; ++c) canvas.Text(margin + c * (w + margin), 4, titles[c], {0, 0, 0}, 1);
  for (size_t r = 0; r < sheet.size(); ++r) {
    const int y = header + static_cast<int>(r) * (h + margin);
    const Image8* panels[] = {&sheet[r].gt, &sheet[r].ours, &sheet[r].basecolor,
                              &sheet[r].irradiance};
    for (int c = 0; c < 4; ++c) {
      if (!panels[c]->empty()) Blit(*panels[c], &sheet_image, margin + c * (w + margin), y);
    }
    canvas.Text(margin + 2, y + 2, absl::StrCat("F", sheet[r].frame), {255, 255, 0}, 1);
  }
  return fd::client::WritePng((out / "contact_sheet.png").string(), sheet_image);
}

}  // namespace fd::evaluate

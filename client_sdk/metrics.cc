#include "client_sdk/metrics.h"

#include <array>
#include <cmath>
#include <limits>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"

namespace fd::client {
namespace {

absl::Status CheckSameShape(const ImageF& a, const ImageF& b) {
  if (a.width != b.width || a.height != b.height || a.channels != b.channels) {
    return absl::InvalidArgumentError(absl::StrCat("images differ in shape: ", a.width, "x",
                                                   a.height, "x", a.channels, " vs ", b.width, "x",
                                                   b.height, "x", b.channels));
  }
  if (a.pixels.empty()) return absl::InvalidArgumentError("images are empty");
  return absl::OkStatus();
}

std::array<double, kSsimWindow> MakeTaps() {
  std::array<double, kSsimWindow> taps{};
  const double sigma = 1.5;
  double sum = 0.0;
  for (int i = 0; i < kSsimWindow; ++i) {
    const double d = i - kSsimWindow / 2;
    taps[i] = std::exp(-(d * d) / (2.0 * sigma * sigma));
    sum += taps[i];
  }
  for (double& t : taps) t /= sum;
  return taps;
}

// Separable "valid" Gaussian filter of one plane: [h][w] -> [h-10][w-10].
std::vector<double> FilterValid(const std::vector<double>& plane, int width, int height) {
  const double* taps = SsimGaussianTaps();
  const int out_w = width - kSsimWindow + 1;
  const int out_h = height - kSsimWindow + 1;
  std::vector<double> rows(size_t(height) * out_w);
  for (int y = 0; y < height; ++y) {
    for (int x = 0; x < out_w; ++x) {
      double sum = 0.0;
      for (int k = 0; k < kSsimWindow; ++k) sum += taps[k] * plane[size_t(y) * width + x + k];
      rows[size_t(y) * out_w + x] = sum;
    }
  }
  std::vector<double> out(size_t(out_h) * out_w);
  for (int y = 0; y < out_h; ++y) {
    for (int x = 0; x < out_w; ++x) {
      double sum = 0.0;
      for (int k = 0; k < kSsimWindow; ++k) sum += taps[k] * rows[size_t(y + k) * out_w + x];
      out[size_t(y) * out_w + x] = sum;
    }
  }
  return out;
}

}  // namespace

const double* SsimGaussianTaps() {
  static const std::array<double, kSsimWindow> taps = MakeTaps();
  return taps.data();
}

absl::StatusOr<double> Psnr(const ImageF& a, const ImageF& b) {
  if (absl::Status s = CheckSameShape(a, b); !s.ok()) return s;
  double sum = 0.0;
  for (size_t i = 0; i < a.pixels.size(); ++i) {
    const double d = double(a.pixels[i]) - double(b.pixels[i]);
    sum += d * d;
  }
  const double mse = sum / double(a.pixels.size());
  if (mse == 0.0) return std::numeric_limits<double>::infinity();
  return 10.0 * std::log10(1.0 / mse);
}

absl::StatusOr<double> Ssim(const ImageF& a, const ImageF& b) {
  if (absl::Status s = CheckSameShape(a, b); !s.ok()) return s;
  if (a.width < kSsimWindow || a.height < kSsimWindow) {
    return absl::InvalidArgumentError(absl::StrCat("SSIM needs images of at least ", kSsimWindow,
                                                   "x", kSsimWindow, " pixels, got ", a.width, "x",
                                                   a.height));
  }
  const double c1 = (0.01 * 1.0) * (0.01 * 1.0);
  const double c2 = (0.03 * 1.0) * (0.03 * 1.0);
  const size_t plane_size = size_t(a.width) * a.height;
  double total = 0.0;
  for (int c = 0; c < a.channels; ++c) {
    std::vector<double> x(plane_size), y(plane_size), xx(plane_size), yy(plane_size),
        xy(plane_size);
    for (size_t p = 0; p < plane_size; ++p) {
      x[p] = a.pixels[p * a.channels + c];
      y[p] = b.pixels[p * b.channels + c];
      xx[p] = x[p] * x[p];
      yy[p] = y[p] * y[p];
      xy[p] = x[p] * y[p];
    }
    const std::vector<double> mu_x = FilterValid(x, a.width, a.height);
    const std::vector<double> mu_y = FilterValid(y, a.width, a.height);
    const std::vector<double> e_xx = FilterValid(xx, a.width, a.height);
    const std::vector<double> e_yy = FilterValid(yy, a.width, a.height);
    const std::vector<double> e_xy = FilterValid(xy, a.width, a.height);
    double sum = 0.0;
    for (size_t i = 0; i < mu_x.size(); ++i) {
      const double mx = mu_x[i], my = mu_y[i];
      const double var_x = e_xx[i] - mx * mx;
      const double var_y = e_yy[i] - my * my;
      const double cov = e_xy[i] - mx * my;
      sum += ((2.0 * mx * my + c1) * (2.0 * cov + c2)) /
             ((mx * mx + my * my + c1) * (var_x + var_y + c2));
    }
    total += sum / double(mu_x.size());
  }
  return total / a.channels;
}

}  // namespace fd::client

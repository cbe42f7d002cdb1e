// PSNR / SSIM against analytically known values (client_sdk/metrics.h).
#include "client_sdk/metrics.h"

#include <gtest/gtest.h>

#include <array>
#include <cmath>

#include "tests/client_sdk/test_util.h"

namespace fd::client {
namespace {

using testing::PatternF;

constexpr double kC1 = 0.01 * 0.01;  // (K1 L)^2 with L = 1
constexpr double kC2 = 0.03 * 0.03;  // (K2 L)^2

ImageF Constant(int size, int channels, const std::vector<float>& per_channel) {
  ImageF image(size, size, channels);
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      for (int c = 0; c < channels; ++c) image.at(x, y, c) = per_channel[c];
    }
  }
  return image;
}

TEST(PsnrTest, IdenticalImagesAreInfinite) {
  const ImageF a = PatternF(20, 20, 3, 1);
  absl::StatusOr<double> psnr = Psnr(a, a);
  ASSERT_TRUE(psnr.ok());
  EXPECT_TRUE(std::isinf(*psnr) && *psnr > 0);
}

TEST(PsnrTest, KnownNoiseLevel) {
  // y = x +- 5/255 on every element: MSE = (5/255)^2, so
  // PSNR = 10 log10(255^2 / 25) = 20 log10(51) dB (about 34.15).
  Image8 x(32, 24, 3);
  Image8 y(32, 24, 3);
  for (size_t i = 0; i < x.pixels.size(); ++i) {
    x.pixels[i] = static_cast<uint8_t>(10 + (i * 37) % 236);
    y.pixels[i] = static_cast<uint8_t>(i % 2 == 0 ? x.pixels[i] + 5 : x.pixels[i] - 5);
  }
  absl::StatusOr<double> psnr = Psnr(ToFloat(ImageView::Of(x)), ToFloat(ImageView::Of(y)));
  ASSERT_TRUE(psnr.ok());
  EXPECT_NEAR(*psnr, 20.0 * std::log10(51.0), 1e-5);  // float32 inputs
}

TEST(PsnrTest, ShapeMismatch) {
  EXPECT_EQ(Psnr(PatternF(4, 4, 3, 1), PatternF(4, 4, 1, 1)).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST(SsimTest, IdenticalImagesGiveOne) {
  const ImageF a = PatternF(40, 30, 3, 2);
  absl::StatusOr<double> ssim = Ssim(a, a);
  ASSERT_TRUE(ssim.ok());
  EXPECT_DOUBLE_EQ(*ssim, 1.0);
}

TEST(SsimTest, ConstantImagesGiveTheLuminanceTerm) {
  // No variance: SSIM = (2ab + C1) / (a^2 + b^2 + C1), per channel averaged.
  const std::vector<float> a = {0.25f, 0.5f, 0.875f}, b = {0.625f, 0.5f, 0.125f};
  absl::StatusOr<double> ssim = Ssim(Constant(16, 3, a), Constant(16, 3, b));
  ASSERT_TRUE(ssim.ok());
  double expected = 0.0;
  for (int c = 0; c < 3; ++c) {
    expected += (2.0 * a[c] * b[c] + kC1) / (double(a[c]) * a[c] + double(b[c]) * b[c] + kC1) / 3.0;
  }
  EXPECT_NEAR(*ssim, expected, 1e-12);
}

TEST(SsimTest, CheckerboardsHaveClosedFormStatistics) {
  // x = m + d s, y = m2 + e s with s = (-1)^(i+j). Under the separable
  // window with 1-D taps t, the window whose top-left pixel has sign sv has
  //   mu_x = m + d sv G, mu_y = m2 + e sv G, G = (sum_k t_k (-1)^k)^2,
  //   var_x = d^2 (1 - G^2), var_y = e^2 (1 - G^2), cov = d e (1 - G^2),
  // so every term of SSIM is known; half the windows have each sign.
  const double m = 0.5, d = 0.25, m2 = 0.375, e = -0.125;  // exact in float
  const int size = 26;                                     // 16 x 16 windows
  ImageF x(size, size, 1), y(size, size, 1);
  for (int j = 0; j < size; ++j) {
    for (int i = 0; i < size; ++i) {
      const double s = (i + j) % 2 == 0 ? 1.0 : -1.0;
      x.at(i, j, 0) = static_cast<float>(m + d * s);
      y.at(i, j, 0) = static_cast<float>(m2 + e * s);
    }
  }
  // The Gaussian taps, computed independently of the implementation.
  std::array<double, 11> taps;
  double sum = 0.0;
  for (int k = 0; k < 11; ++k) {
    taps[k] = std::exp(-double((k - 5) * (k - 5)) / (2.0 * 1.5 * 1.5));
    sum += taps[k];
  }
  double alternating = 0.0;
  for (int k = 0; k < 11; ++k) alternating += (k % 2 == 0 ? 1.0 : -1.0) * taps[k] / sum;
  const double g = alternating * alternating;
  const double spread = 1.0 - g * g;
  const double cs = (2.0 * d * e * spread + kC2) / ((d * d + e * e) * spread + kC2);
  double expected = 0.0;
  for (double sv : {1.0, -1.0}) {
    const double mx = m + d * sv * g, my = m2 + e * sv * g;
    expected += 0.5 * (2.0 * mx * my + kC1) / (mx * mx + my * my + kC1) * cs;
  }
  absl::StatusOr<double> ssim = Ssim(x, y);
  ASSERT_TRUE(ssim.ok());
  EXPECT_NEAR(*ssim, expected, 1e-9);
  EXPECT_LT(*ssim, 0.0);  // anti-correlated structure
}

TEST(SsimTest, RejectsSmallOrMismatchedImages) {
  EXPECT_EQ(Ssim(PatternF(10, 20, 1, 1), PatternF(10, 20, 1, 1)).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(Ssim(PatternF(20, 20, 1, 1), PatternF(20, 21, 1, 1)).status().code(),
            absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace fd::client

// Image quality metrics for `framediffuser-client eval`: PSNR and SSIM.
//
// Both take float images in [0, 1] (uint8 images divided by 255), so a data
// range of 1. Colour images are compared on every channel:
//  - PSNR = 10 log10(1 / MSE), the MSE taken over all pixels and channels;
//    +inf for identical images.
//  - SSIM as in Wang et al. 2004 (and their reference ssim_index.m): an 11x11
//    Gaussian window with sigma 1.5 (normalised to sum 1), K1 = 0.01,
//    K2 = 0.03, L = 1, population (not sample) statistics, evaluated only
//    where the window fits inside the image ("valid"), averaged over the map;
//    for several channels the per-channel means are averaged (what
//    skimage.metrics.structural_similarity does with channel_axis and
//    gaussian_weights=True, use_sample_covariance=False).
// Thread-safe, no shared state.
#ifndef FD_CLIENT_SDK_METRICS_H_
#define FD_CLIENT_SDK_METRICS_H_

#include "absl/status/statusor.h"
#include "client_sdk/image.h"

namespace fd::client {

// INVALID_ARGUMENT when the images differ in width, height or channels.
absl::StatusOr<double> Psnr(const ImageF& a, const ImageF& b);

// INVALID_ARGUMENT when the shapes differ or an image is smaller than 11x11.
absl::StatusOr<double> Ssim(const ImageF& a, const ImageF& b);

// The 1-D Gaussian of the SSIM window (11 taps, sigma 1.5, sum 1); the 2-D
// window is its outer product.
const double* SsimGaussianTaps();
inline constexpr int kSsimWindow = 11;

}  // namespace fd::client

#endif  // FD_CLIENT_SDK_METRICS_H_

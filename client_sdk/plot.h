// Line plots of per-frame metrics (PSNR, SSIM) over frame numbers, drawn into
// an RGB image for `framediffuser-client eval --plot`: one panel per series,
// stacked, sharing the frame axis, each with a y axis, grid, tick labels, the
// series line and a dashed line at its mean.
#ifndef FD_CLIENT_SDK_PLOT_H_
#define FD_CLIENT_SDK_PLOT_H_

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "client_sdk/image.h"
#include "client_sdk/raster.h"

namespace fd::client {

struct PlotSeries {
  std::string title;           // e.g. "PSNR (dB)"
  std::vector<double> values;  // one per frame; +inf is drawn at the top edge
  Rgb color;
};

// INVALID_ARGUMENT when there are no frames or series, a series length
// differs from frames.size(), or the image is too small (< 320x200).
// `x_title` labels the shared axis (e.g. "STEP" for a loss curve).
absl::StatusOr<Image8> PlotOverFrames(const std::vector<int64_t>& frames,
                                      const std::vector<PlotSeries>& series, int width = 960,
                                      int height = 540, const std::string& x_title = "FRAME");

// A "nice" tick step (1, 2 or 5 times a power of ten) giving about `ticks`
// intervals over `range`.
double NiceTickStep(double range, int ticks);

}  // namespace fd::client

#endif  // FD_CLIENT_SDK_PLOT_H_

#include "client_sdk/plot.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"

namespace fd::client {
namespace {

constexpr Rgb kBackground{255, 255, 255};
constexpr Rgb kAxis{40, 40, 40};
constexpr Rgb kGrid{225, 225, 225};
constexpr Rgb kText{20, 20, 20};
constexpr int kScale = 2;  // font pixel size

int DecimalsFor(double step) {
  return step >= 1.0 ? 0 : static_cast<int>(std::ceil(-std::log10(step) - 1e-9));
}

struct Rect {
  int x0, y0, x1, y1;  // inclusive plot area
};

void DrawPanel(Canvas& canvas, const Rect& area, const std::vector<int64_t>& frames,
               const PlotSeries& series, double x_min, double x_max, double x_step, bool x_labels) {
  // Y range from the finite values, padded, snapped to ticks.
  double lo = std::numeric_limits<double>::infinity();
  double hi = -lo;
  double sum = 0.0;
  int finite = 0;
  bool any_inf = false;
  for (double v : series.values) {
    if (std::isfinite(v)) {
      lo = std::min(lo, v);
      hi = std::max(hi, v);
      sum += v;
      ++finite;
    } else {
      any_inf = true;
    }
  }
  if (finite == 0) {
    lo = 0.0;
    hi = 1.0;
  }
  if (hi - lo < 1e-9) {
    const double pad = std::max(std::abs(hi) * 0.05, 0.01);
    lo -= pad;
    hi += pad;
  }
  const double y_step = NiceTickStep(hi - lo, 5);
  lo = std::floor(lo / y_step) * y_step;
  hi = std::ceil(hi / y_step) * y_step;
  const int decimals = DecimalsFor(y_step);

  auto px = [&](double x) {
    if (x_max <= x_min) return (area.x0 + area.x1) / 2;
    return area.x0 +
           static_cast<int>(std::lround((x - x_min) / (x_max - x_min) * (area.x1 - area.x0)));
  };
  auto py = [&](double y) {
    if (!std::isfinite(y)) return area.y0;  // +inf at the top edge
    return area.y1 - static_cast<int>(std::lround((y - lo) / (hi - lo) * (area.y1 - area.y0)));
  };

  // Grid and y labels.
  for (double y = lo; y <= hi + y_step * 1e-6; y += y_step) {
    const int yy = py(y);
    canvas.Line(area.x0, yy, area.x1, yy, kGrid);
    const std::string label = absl::StrFormat("%.*f", decimals, y);
    canvas.Text(area.x0 - 8 - Canvas::TextWidth(label, kScale), yy - Canvas::TextHeight(kScale) / 2,
                label, kText, kScale);
  }
  for (double x = x_min; x <= x_max + 1e-9; x += x_step) {
    const int xx = px(x);
    canvas.Line(xx, area.y0, xx, area.y1, kGrid);
    if (x_labels) {
      const std::string label = absl::StrCat(static_cast<int64_t>(std::llround(x)));
      canvas.Text(xx - Canvas::TextWidth(label, kScale) / 2, area.y1 + 8, label, kText, kScale);
    }
  }
  // Axes.
  canvas.Line(area.x0, area.y0, area.x0, area.y1, kAxis, 2);
  canvas.Line(area.x0, area.y1, area.x1, area.y1, kAxis, 2);

  // Title with the mean.
  std::string title = series.title;
  if (finite > 0) {
    absl::StrAppend(&title, "   MEAN ", absl::StrFormat("%.*f", decimals + 2, sum / finite));
  }
  if (any_inf) absl::StrAppend(&title, "   (INF AT TOP)");
  canvas.Text(area.x0, area.y0 - Canvas::TextHeight(kScale) - 8, title, series.color, kScale);

  // Mean line, then the series.
  if (finite > 0) {
    const int ym = py(sum / finite);
    canvas.Line(area.x0, ym, area.x1, ym, series.color, 1, 6);
  }
  for (size_t i = 0; i < frames.size(); ++i) {
    const int x = px(static_cast<double>(frames[i]));
    const int y = py(series.values[i]);
    if (i > 0) {
      canvas.Line(px(static_cast<double>(frames[i - 1])), py(series.values[i - 1]), x, y,
                  series.color, 2);
    }
    if (frames.size() <= 60) canvas.FillRect(x - 2, y - 2, x + 2, y + 2, series.color);
  }
}

}  // namespace

double NiceTickStep(double range, int ticks) {
  if (!(range > 0.0) || ticks <= 0) return 1.0;
  const double raw = range / ticks;
  const double magnitude = std::pow(10.0, std::floor(std::log10(raw)));
  const double normalised = raw / magnitude;
  const double nice = normalised < 1.5   ? 1.0
                      : normalised < 3.0 ? 2.0
                      : normalised < 7.0 ? 5.0
                                         : 10.0;
  return nice * magnitude;
}

absl::StatusOr<Image8> PlotOverFrames(const std::vector<int64_t>& frames,
                                      const std::vector<PlotSeries>& series, int width, int height,
                                      const std::string& x_title) {
  if (frames.empty() || series.empty()) {
    return absl::InvalidArgumentError("plot needs at least one frame and one series");
  }
  for (const PlotSeries& s : series) {
    if (s.values.size() != frames.size()) {
      return absl::InvalidArgumentError(absl::StrCat("series '", s.title, "' has ", s.values.size(),
                                                     " values for ", frames.size(), " frames"));
    }
  }
  if (width < 320 || height < 200) {
    return absl::InvalidArgumentError(
        absl::StrCat("plot size must be at least 320x200, got ", width, "x", height));
  }
  Image8 image(width, height, 3);
  Canvas canvas(&image);
  canvas.Fill(kBackground);

  const double x_min = static_cast<double>(frames.front());
  const double x_max = static_cast<double>(frames.back());
  const double x_step = std::max(1.0, NiceTickStep(x_max - x_min, 8));

  const int left = 100, right = 30, top = 40, bottom = 70, gap = 50;
  const int panels = static_cast<int>(series.size());
  const int panel_height = (height - top - bottom - gap * (panels - 1)) / panels;
  for (int i = 0; i < panels; ++i) {
    const int y0 = top + i * (panel_height + gap);
    const Rect area{left, y0, width - right, y0 + panel_height};
    DrawPanel(canvas, area, frames, series[i], x_min, x_max, x_step, i == panels - 1);
  }
  canvas.Text((left + width - right) / 2 - Canvas::TextWidth(x_title, kScale) / 2,
              height - Canvas::TextHeight(kScale) - 10, x_title, kText, kScale);
  return image;
}

}  // namespace fd::client

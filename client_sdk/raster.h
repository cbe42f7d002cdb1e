// A tiny software rasteriser for the metric plots: filled rectangles, thick
// lines and text in a built-in 5x7 pixel font (digits, A-Z, a few symbols;
// lower case is drawn as upper case). Deliberately minimal: no anti-aliasing.
#ifndef FD_CLIENT_SDK_RASTER_H_
#define FD_CLIENT_SDK_RASTER_H_

#include <cstdint>
#include <string_view>

#include "client_sdk/image.h"

namespace fd::client {

struct Rgb {
  uint8_t r = 0, g = 0, b = 0;
};

// Draws into an RGB Image8; everything is clipped to the image.
class Canvas {
 public:
  explicit Canvas(Image8* image) : image_(image) {}

  void Fill(Rgb color);
  void FillRect(int x0, int y0, int x1, int y1, Rgb color);  // inclusive corners
  // A line `thickness` pixels wide (square brush); `dash` > 0 draws dashes of
  // that many pixels.
  void Line(int x0, int y0, int x1, int y1, Rgb color, int thickness = 1, int dash = 0);
  // Text with its top-left corner at (x, y); each font pixel is scale x scale.
  void Text(int x, int y, std::string_view text, Rgb color, int scale = 2);
  // Width in pixels of Text(..., scale).
  static int TextWidth(std::string_view text, int scale = 2);
  static int TextHeight(int scale = 2) { return 7 * scale; }

  void Set(int x, int y, Rgb color);

 private:
  Image8* image_;
};

}  // namespace fd::client

#endif  // FD_CLIENT_SDK_RASTER_H_

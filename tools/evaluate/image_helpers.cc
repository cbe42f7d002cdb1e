#include "tools/evaluate/image_helpers.h"

#include <torch/torch.h>

#include <cstring>

namespace fd::evaluate {

using fd::client::Image8;
using fd::client::ImageF;

ImageF ToUnitFloat(const Image8& image) {
  ImageF out(image.width, image.height, image.channels);
  for (size_t i = 0; i < image.pixels.size(); ++i) out.pixels[i] = image.pixels[i] / 255.0f;
  return out;
}

std::vector<Image8> DecodedToImages(const torch::Tensor& decoded) {
  const torch::Tensor bytes = ((decoded / 2 + 0.5).clamp(0, 1) * 255)
                                  .round()
                                  .to(torch::kUInt8)
                                  .permute({0, 2, 3, 1})
                                  .contiguous();
  std::vector<Image8> out;
  for (int64_t i = 0; i < bytes.size(0); ++i) {
    Image8 image(static_cast<int>(bytes.size(2)), static_cast<int>(bytes.size(1)), 3);
    std::memcpy(image.pixels.data(), bytes[i].data_ptr<uint8_t>(), image.pixels.size());
    out.push_back(std::move(image));
  }
  return out;
}

void Blit(const Image8& panel, Image8* sheet, int x0, int y0) {
  for (int y = 0; y < panel.height; ++y) {
    for (int x = 0; x < panel.width; ++x) {
      for (int c = 0; c < 3; ++c) {
        sheet->at(x0 + x, y0 + y, c) = panel.at(x, y, panel.channels == 1 ? 0 : c);
      }
    }
  }
}

}  // namespace fd::evaluate

#include "client_sdk/irradiance.h"

#include <algorithm>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"

namespace fd::client {

absl::StatusOr<Image8> IrradianceMap(const Image8& previous_output,
                                     const Image8& previous_basecolor) {
  const Image8& out = previous_output;
  const Image8& albedo = previous_basecolor;
  if (out.channels != 3 || albedo.channels != 3 || out.width != albedo.width ||
      out.height != albedo.height || out.pixels.empty()) {
    return absl::InvalidArgumentError(absl::StrCat(
        "irradiance needs two RGB images of equal size, got ", out.width, "x", out.height, "x",
        out.channels, " and ", albedo.width, "x", albedo.height, "x", albedo.channels));
  }
  Image8 result(out.width, out.height, 1);
  for (size_t p = 0; p < result.pixels.size(); ++p) {
    // float32 arithmetic, as the reference does it with torch tensors.
    const float final_luma = 0.299f * (out.pixels[3 * p] / 255.0f) +
                             0.587f * (out.pixels[3 * p + 1] / 255.0f) +
                             0.114f * (out.pixels[3 * p + 2] / 255.0f);
    const float albedo_luma = 0.299f * (albedo.pixels[3 * p] / 255.0f) +
                              0.587f * (albedo.pixels[3 * p + 1] / 255.0f) +
                              0.114f * (albedo.pixels[3 * p + 2] / 255.0f);
    const float irradiance = albedo_luma > 0.01f ? final_luma / (albedo_luma + 1e-6f) : 2.0f;
    const float normalised = std::clamp(irradiance, 0.0f, 2.0f) / 2.0f;
    // numpy's astype(np.uint8) truncates.
    result.pixels[p] = static_cast<uint8_t>(normalised * 255.0f);
  }
  return result;
}

}  // namespace fd::client

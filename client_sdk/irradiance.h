// The irradiance estimate FrameDiffuser feeds its model (the authors'
// GBufferDataset.create_irradiance_map), recomputed client-side for the
// side-by-side video: how lit the previous frame was relative to its albedo.
#ifndef FD_CLIENT_SDK_IRRADIANCE_H_
#define FD_CLIENT_SDK_IRRADIANCE_H_

#include "absl/status/statusor.h"
#include "client_sdk/image.h"

namespace fd::client {

// Per pixel, with luma = 0.299 R + 0.587 G + 0.114 B of values / 255:
//   irradiance = luma(previous_output) / (luma(previous_basecolor) + 1e-6)
//                where luma(previous_basecolor) > 0.01, else 2.0;
//   result = uint8(trunc(clamp(irradiance, 0, 2) / 2 * 255)).
// Both inputs RGB (3 channels) of equal size; the result has 1 channel.
// INVALID_ARGUMENT otherwise. Thread-safe.
absl::StatusOr<Image8> IrradianceMap(const Image8& previous_output,
                                     const Image8& previous_basecolor);

}  // namespace fd::client

#endif  // FD_CLIENT_SDK_IRRADIANCE_H_

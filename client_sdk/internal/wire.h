// Internal: conversions between the SDK's types and the wire messages
// (framediffuser.v1), and between gRPC and absl statuses.
#ifndef FD_CLIENT_SDK_INTERNAL_WIRE_H_
#define FD_CLIENT_SDK_INTERNAL_WIRE_H_

#include <grpcpp/support/status.h>

#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "client_sdk/client.h"
#include "client_sdk/session.h"
#include "framediffuser/v1/render_service.pb.h"

namespace fd::client::internal {

namespace v1 = ::framediffuser::v1;

// Same code (the canonical codes are shared) and message.
absl::Status FromGrpc(const grpc::Status& status);
// The canonical code of an int (FrameError.code); UNKNOWN when out of range.
absl::StatusCode CodeFromInt(int code);

// Copies `view` into `out` with `channels` channels, checking its shape:
// `field` names it in errors (e.g. "frame.gbuffer.depth"). Colour fields
// (channels 3) accept 4-channel views and drop alpha; scalar fields accept a
// multi-channel view with select_channel set. When width/height are > 0 the
// view must have that size. INVALID_ARGUMENT on any mismatch.
absl::Status FillImage(const ImageView& view, int channels, uint32_t width, uint32_t height,
                       const std::string& field, Compression compression, int zstd_level,
                       v1::Image* out);

// Decodes a wire image's payload (decompressing zstd) into raw bytes, moving
// them out of `image` when uncompressed. DATA_LOSS on a length mismatch or
// bad zstd; `field` names it.
absl::StatusOr<std::string> TakeImageBytes(v1::Image* image, const std::string& field);

// A view of raw bytes that hold a wire image's elements.
ImageView ViewOfBytes(const std::string& bytes, const v1::Image& shape);

// DType <-> v1::DType; INVALID_ARGUMENT for DTYPE_UNSPECIFIED in FromWire.
v1::DType ToWire(DType dtype);
absl::StatusOr<DType> FromWire(v1::DType dtype);
v1::Compression ToWire(Compression compression);
Compression FromWire(v1::Compression compression);
v1::Scheduler ToWire(Scheduler scheduler);
Scheduler FromWire(v1::Scheduler scheduler);
v1::SkyMode ToWire(SkyMode sky_mode);
SkyMode FromWire(v1::SkyMode sky_mode);
Readiness FromWire(v1::Readiness readiness);

Environment FromWire(const v1::Environment& environment);
SessionSettings FromWire(const v1::SessionSettings& settings);
StageTimings FromWire(const v1::StageTimings& timings);

}  // namespace fd::client::internal

#endif  // FD_CLIENT_SDK_INTERNAL_WIRE_H_

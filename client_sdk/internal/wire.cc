#include "client_sdk/internal/wire.h"

#include <zstd.h>

#include <cstring>

#include "absl/strings/str_cat.h"

namespace fd::client::internal {
namespace {

// Copies `channels` channels starting at `first` of every pixel.
void CopyPixels(const ImageView& view, int first, int channels, char* out) {
  const size_t element = DTypeSize(view.dtype);
  const size_t out_row = size_t(view.width) * channels * element;
  if (first == 0 && channels == view.channels) {
    for (int y = 0; y < view.height; ++y) {
      std::memcpy(out + size_t(y) * out_row, view.row(y), out_row);
    }
    return;
  }
  const size_t in_pixel = size_t(view.channels) * element;
  const size_t out_pixel = size_t(channels) * element;
  for (int y = 0; y < view.height; ++y) {
    const uint8_t* src = view.row(y) + size_t(first) * element;
    char* dst = out + size_t(y) * out_row;
    for (int x = 0; x < view.width; ++x) {
      std::memcpy(dst + size_t(x) * out_pixel, src + size_t(x) * in_pixel, out_pixel);
    }
  }
}

}  // namespace

absl::StatusCode CodeFromInt(int code) {
  if (code < 0 || code > static_cast<int>(absl::StatusCode::kUnauthenticated)) {
    return absl::StatusCode::kUnknown;
  }
  return static_cast<absl::StatusCode>(code);
}

absl::Status FromGrpc(const grpc::Status& status) {
  if (status.ok()) return absl::OkStatus();
  return absl::Status(CodeFromInt(static_cast<int>(status.error_code())), status.error_message());
}

absl::Status FillImage(const ImageView& view, int channels, uint32_t width, uint32_t height,
                       const std::string& field, Compression compression, int zstd_level,
                       v1::Image* out) {
  if (view.empty()) return absl::InvalidArgumentError(absl::StrCat(field, ": missing"));
  if (view.width <= 0 || view.height <= 0 || view.channels <= 0) {
    return absl::InvalidArgumentError(
        absl::StrCat(field, ": bad shape ", view.width, "x", view.height, "x", view.channels));
  }
  if (width > 0 && height > 0 &&
      (uint32_t(view.width) != width || uint32_t(view.height) != height)) {
    return absl::InvalidArgumentError(absl::StrCat(field, ": expected the session's size ", width,
                                                   "x", height, ", got ", view.width, "x",
                                                   view.height));
  }
  if (view.row_stride_bytes != 0 && view.row_stride_bytes < view.packed_row_bytes()) {
    return absl::InvalidArgumentError(absl::StrCat(field, ": row_stride_bytes ",
                                                   view.row_stride_bytes, " < ",
                                                   view.packed_row_bytes(), " bytes of pixels"));
  }
  int first = 0;
  if (channels == 3) {
    if (view.channels != 3 && view.channels != 4) {
      return absl::InvalidArgumentError(absl::StrCat(
          field, ": expected 3 channels (RGB) or 4 (RGBA, alpha dropped), got ", view.channels));
    }
  } else if (view.select_channel >= 0) {
    if (view.select_channel >= view.channels) {
      return absl::InvalidArgumentError(absl::StrCat(field, ": select_channel ",
                                                     view.select_channel, " but the view has ",
                                                     view.channels, " channels"));
    }
    first = view.select_channel;
  } else if (view.channels != channels) {
    return absl::InvalidArgumentError(
        absl::StrCat(field, ": expected ", channels, " channel, got ", view.channels,
                     " (set ImageView::select_channel to send one of them)"));
  }
  out->set_width(static_cast<uint32_t>(view.width));
  out->set_height(static_cast<uint32_t>(view.height));
  out->set_channels(static_cast<uint32_t>(channels));
  out->set_dtype(ToWire(view.dtype));
  const size_t bytes = size_t(view.width) * view.height * channels * DTypeSize(view.dtype);
  if (compression == Compression::kZstd) {
    std::string raw(bytes, '\0');
    CopyPixels(view, first, channels, raw.data());
    std::string* data = out->mutable_data();
    data->resize(ZSTD_compressBound(bytes));
    const size_t written =
        ZSTD_compress(data->data(), data->size(), raw.data(), raw.size(), zstd_level);
    if (ZSTD_isError(written)) {
      return absl::InternalError(
          absl::StrCat(field, ": zstd compression failed: ", ZSTD_getErrorName(written)));
    }
    data->resize(written);
    out->set_compression(v1::COMPRESSION_ZSTD);
  } else {
    std::string* data = out->mutable_data();
    data->resize(bytes);
    CopyPixels(view, first, channels, data->data());
    out->set_compression(v1::COMPRESSION_NONE);
  }
  return absl::OkStatus();
}

absl::StatusOr<std::string> TakeImageBytes(v1::Image* image, const std::string& field) {
  absl::StatusOr<DType> dtype = FromWire(image->dtype());
  if (!dtype.ok()) return absl::DataLossError(absl::StrCat(field, ": ", dtype.status().message()));
  const size_t expected =
      size_t(image->width()) * image->height() * image->channels() * DTypeSize(*dtype);
  if (expected == 0) {
    return absl::DataLossError(absl::StrCat(field, ": empty image ", image->width(), "x",
                                            image->height(), "x", image->channels()));
  }
  std::string bytes;
  if (image->compression() == v1::COMPRESSION_ZSTD) {
    const unsigned long long content =
        ZSTD_getFrameContentSize(image->data().data(), image->data().size());
    if (content != expected) {
      return absl::DataLossError(
          absl::StrCat(field, ": zstd frame holds ", content, " bytes, expected ", expected));
    }
    bytes.resize(expected);
    const size_t got =
        ZSTD_decompress(bytes.data(), bytes.size(), image->data().data(), image->data().size());
    if (ZSTD_isError(got) || got != expected) {
      return absl::DataLossError(absl::StrCat(
          field, ": bad zstd data: ", ZSTD_isError(got) ? ZSTD_getErrorName(got) : "short"));
    }
    return bytes;
  }
  if (image->data().size() != expected) {
    return absl::DataLossError(
        absl::StrCat(field, ": ", image->data().size(), " bytes, expected ", expected));
  }
  bytes.swap(*image->mutable_data());  // no copy
  return bytes;
}

ImageView ViewOfBytes(const std::string& bytes, const v1::Image& shape) {
  absl::StatusOr<DType> dtype = FromWire(shape.dtype());
  return ImageView::Raw(bytes.data(), static_cast<int>(shape.width()),
                        static_cast<int>(shape.height()), static_cast<int>(shape.channels()),
                        dtype.ok() ? *dtype : DType::kUint8);
}

v1::DType ToWire(DType dtype) {
  switch (dtype) {
    case DType::kUint8:
      return v1::DTYPE_UINT8;
    case DType::kFloat16:
      return v1::DTYPE_FLOAT16;
    case DType::kFloat32:
      return v1::DTYPE_FLOAT32;
  }
  return v1::DTYPE_UNSPECIFIED;
}

absl::StatusOr<DType> FromWire(v1::DType dtype) {
  switch (dtype) {
    case v1::DTYPE_UINT8:
      return DType::kUint8;
    case v1::DTYPE_FLOAT16:
      return DType::kFloat16;
    case v1::DTYPE_FLOAT32:
      return DType::kFloat32;
    default:
      return absl::InvalidArgumentError(
          absl::StrCat("unsupported dtype ", static_cast<int>(dtype)));
  }
}

v1::Compression ToWire(Compression compression) {
  return compression == Compression::kZstd ? v1::COMPRESSION_ZSTD : v1::COMPRESSION_NONE;
}

Compression FromWire(v1::Compression compression) {
  return compression == v1::COMPRESSION_ZSTD ? Compression::kZstd : Compression::kNone;
}

v1::Scheduler ToWire(Scheduler scheduler) {
  switch (scheduler) {
    case Scheduler::kDefault:
      return v1::SCHEDULER_UNSPECIFIED;
    case Scheduler::kUniPC:
      return v1::SCHEDULER_UNIPC;
    case Scheduler::kDpmSolverPP2M:
      return v1::SCHEDULER_DPM_SOLVER_PP_2M;
    case Scheduler::kDdim:
      return v1::SCHEDULER_DDIM;
    case Scheduler::kEuler:
      return v1::SCHEDULER_EULER;
  }
  return v1::SCHEDULER_UNSPECIFIED;
}

Scheduler FromWire(v1::Scheduler scheduler) {
  switch (scheduler) {
    case v1::SCHEDULER_UNIPC:
      return Scheduler::kUniPC;
    case v1::SCHEDULER_DPM_SOLVER_PP_2M:
      return Scheduler::kDpmSolverPP2M;
    case v1::SCHEDULER_DDIM:
      return Scheduler::kDdim;
    case v1::SCHEDULER_EULER:
      return Scheduler::kEuler;
    default:
      return Scheduler::kDefault;
  }
}

v1::SkyMode ToWire(SkyMode sky_mode) {
  switch (sky_mode) {
    case SkyMode::kDefault:
      return v1::SKY_MODE_UNSPECIFIED;
    case SkyMode::kClientImage:
      return v1::SKY_MODE_CLIENT_IMAGE;
    case SkyMode::kPreviousOutput:
      return v1::SKY_MODE_PREVIOUS_OUTPUT;
    case SkyMode::kOff:
      return v1::SKY_MODE_OFF;
  }
  return v1::SKY_MODE_UNSPECIFIED;
}

SkyMode FromWire(v1::SkyMode sky_mode) {
  switch (sky_mode) {
    case v1::SKY_MODE_CLIENT_IMAGE:
      return SkyMode::kClientImage;
    case v1::SKY_MODE_PREVIOUS_OUTPUT:
      return SkyMode::kPreviousOutput;
    case v1::SKY_MODE_OFF:
      return SkyMode::kOff;
    default:
      return SkyMode::kDefault;
  }
}

Readiness FromWire(v1::Readiness readiness) {
  switch (readiness) {
    case v1::READINESS_LOADING:
      return Readiness::kLoading;
    case v1::READINESS_READY:
      return Readiness::kReady;
    case v1::READINESS_FAILED:
      return Readiness::kFailed;
    case v1::READINESS_UNLOADING:
      return Readiness::kUnloading;
    default:
      return Readiness::kUnknown;
  }
}

Environment FromWire(const v1::Environment& e) {
  Environment out;
  out.name = e.name();
  out.description = e.description();
  out.prompt = e.prompt();
  out.native_width = e.native_width();
  out.native_height = e.native_height();
  out.default_steps = e.default_steps();
  out.max_steps = e.max_steps();
  out.default_scheduler = FromWire(e.default_scheduler());
  out.default_sky_mode = FromWire(e.default_sky_mode());
  out.readiness = FromWire(e.readiness());
  out.readiness_detail = e.readiness_detail();
  out.min_size = e.min_size();
  out.max_size = e.max_size();
  return out;
}

SessionSettings FromWire(const v1::SessionSettings& s) {
  SessionSettings out;
  out.environment = s.environment();
  out.width = s.width();
  out.height = s.height();
  out.seed = s.seed();
  out.steps = s.steps();
  out.scheduler = FromWire(s.scheduler());
  out.sky_mode = FromWire(s.sky_mode());
  absl::StatusOr<DType> dtype = FromWire(s.output_dtype());
  out.output_dtype = dtype.ok() ? *dtype : DType::kUint8;
  out.output_compression = FromWire(s.output_compression());
  out.max_frames_in_flight = s.max_frames_in_flight();
  out.started_from_keyframe = s.started_from_keyframe();
  return out;
}

StageTimings FromWire(const v1::StageTimings& t) {
  StageTimings out;
  out.queue_ms = t.queue_ms();
  out.encode_ms = t.encode_ms();
  out.denoise_ms = t.denoise_ms();
  out.decode_ms = t.decode_ms();
  out.total_ms = t.total_ms();
  out.batch_size = t.batch_size();
  return out;
}

}  // namespace fd::client::internal

// Fuzz target: a dataset image file (PNG or OpenEXR, single image or layered)
// -> client::ReadImageInfo / ReadImage / ListExrLayers / ReadExrLayer, the
// readers the trainer, the evaluation and the CLI use on a dataset folder.
//
// Input: byte 0 picks the format (even: PNG, odd: EXR), the rest is the file.
// The readers take paths, so the bytes go to one file per process in
// $TMPDIR (tmpfs on most machines), rewritten for each input.
// Properties: a decoded image has the size and channel count its header
// reported (ReadImageInfo) and width * height * channels pixels; a bad file
// is DATA_LOSS (or NOT_FOUND for a layer it lacks) with a bounded message.
#include <unistd.h>

#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <fstream>
#include <string>
#include <variant>

#include "client_sdk/image_io.h"
#include "tests/fuzz/fuzz_check.h"

namespace {

std::string ScratchPath(const char* extension) {
  const char* tmp = std::getenv("TMPDIR");
  return std::string(tmp != nullptr && *tmp != '\0' ? tmp : "/tmp") + "/fd_fuzz_image_" +
         std::to_string(::getpid()) + extension;
}

void CheckReadError(const absl::Status& status) {
  FD_FUZZ_CHECK(!status.ok(), "error");
  const absl::StatusCode code = status.code();
  if (code != absl::StatusCode::kDataLoss && code != absl::StatusCode::kNotFound) {
    std::fprintf(stderr, "unexpected status: %s\n", status.ToString().c_str());
  }
  FD_FUZZ_CHECK(code == absl::StatusCode::kDataLoss || code == absl::StatusCode::kNotFound,
                "DATA_LOSS or NOT_FOUND");
  FD_FUZZ_CHECK(status.message().size() <= fd::fuzz::kMaxErrorMessageBytes, "bounded message");
}

template <typename Image>
void CheckImage(const Image& image, const fd::client::ImageFileInfo& info) {
  FD_FUZZ_CHECK(image.width == info.width && image.height == info.height, "size as the header");
  FD_FUZZ_CHECK(image.channels == info.channels, "channels as the header");
  FD_FUZZ_CHECK(image.pixels.size() == size_t(image.width) * image.height * image.channels,
                "pixel count");
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size < 1) return 0;
  const bool exr = (data[0] & 1) != 0;
  static const std::string png_path = ScratchPath(".png");
  static const std::string exr_path = ScratchPath(".exr");
  const std::string& path = exr ? exr_path : png_path;
  {
    std::ofstream out(path, std::ios::binary | std::ios::trunc);
    out.write(reinterpret_cast<const char*>(data) + 1, static_cast<std::streamsize>(size - 1));
    FD_FUZZ_CHECK(out.good(), "scratch file written");
  }

  absl::StatusOr<fd::client::ImageFileInfo> info = fd::client::ReadImageInfo(path);
  absl::StatusOr<fd::client::AnyImage> image = fd::client::ReadImage(path);
  if (!image.ok()) CheckReadError(image.status());
  if (!info.ok()) CheckReadError(info.status());
  if (image.ok() && info.ok()) {
    std::visit([&](const auto& decoded) { CheckImage(decoded, *info); }, *image);
  }
  if (!exr) return 0;

  absl::StatusOr<std::vector<std::string>> layers = fd::client::ListExrLayers(path);
  if (!layers.ok()) {
    CheckReadError(layers.status());
    return 0;
  }
  for (const std::string& layer : *layers) {
    absl::StatusOr<fd::client::ImageFileInfo> layer_info =
        fd::client::ReadExrLayerInfo(path, layer);
    absl::StatusOr<fd::client::ImageF> layer_image = fd::client::ReadExrLayer(path, layer);
    if (!layer_image.ok()) CheckReadError(layer_image.status());
    if (!layer_info.ok()) CheckReadError(layer_info.status());
    if (layer_image.ok() && layer_info.ok()) CheckImage(*layer_image, *layer_info);
  }
  return 0;
}

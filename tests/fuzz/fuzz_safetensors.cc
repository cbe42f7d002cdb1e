// Fuzz target: a .safetensors file's bytes -> model::SafetensorsFile (the
// header's length, JSON, dtypes, shapes and offsets validated before any
// tensor is read), then every tensor read.
//
// Input: the whole file.
// Properties: a file that validates yields, for every key, a tensor of the
// declared shape and dtype whose byte size is the declared [begin, end)
// range; an invalid file is INVALID_ARGUMENT with a bounded message that
// names the file.
#include <cstddef>
#include <cstdint>
#include <string>

#include "model/checkpoint/safetensors.h"
#include "tests/fuzz/fuzz_check.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  absl::StatusOr<std::unique_ptr<fd::model::SafetensorsFile>> file =
      fd::model::SafetensorsFile::FromBuffer("fuzz.safetensors", data, size);
  if (!file.ok()) {
    fd::fuzz::CheckError(file.status(), absl::StatusCode::kInvalidArgument, "");
    FD_FUZZ_CHECK(file.status().message().find("fuzz.safetensors") != absl::string_view::npos,
                  "names the file");
    return 0;
  }
  for (const std::string& key : (*file)->Keys()) {
    absl::StatusOr<fd::model::SafetensorsFile::TensorInfo> info = (*file)->Info(key);
    FD_FUZZ_CHECK(info.ok(), "listed keys have an info");
    FD_FUZZ_CHECK(info->begin <= info->end && info->end <= size, "range inside the file");
    absl::StatusOr<torch::Tensor> tensor = (*file)->Get(key);
    FD_FUZZ_CHECK(tensor.ok(), "a validated tensor reads");
    FD_FUZZ_CHECK(tensor->scalar_type() == info->scalar_type, "dtype");
    FD_FUZZ_CHECK(tensor->sizes().vec() == info->shape, "shape");
    FD_FUZZ_CHECK(
        static_cast<uint64_t>(tensor->numel()) * tensor->element_size() == info->end - info->begin,
        "byte size");
  }
  FD_FUZZ_CHECK(!(*file)->Contains(std::string("\0missing", 8)) || size > 0, "lookup");
  return 0;
}

// Loading training sequences; see training_data.h.
#include "trainer/training_data.h"

#include <torch/torch.h>

#include <atomic>
#include <filesystem>
#include <mutex>
#include <optional>
#include <system_error>
#include <thread>

#include "absl/strings/str_cat.h"
#include "client_sdk/image.h"

namespace fd::trainer {
namespace {

namespace fs = std::filesystem;
using fd::client::AnyImage;
using fd::client::Buffer;
using fd::client::Dataset;
using fd::client::DatasetFrame;

// Decodes every frame of `dataset` into `seq` with `threads` threads.
absl::Status DecodeSequence(const Dataset& dataset, const TrainingDataOptions& options,
                            TrainingSequence& seq) {
  const int64_t count = static_cast<int64_t>(dataset.frames().size());
  const int64_t h = options.height, w = options.width;
  auto u8 = [&](int64_t c) { return torch::empty({count, c, h, w}, torch::kUInt8); };
  seq.final_image = u8(3);
  seq.basecolor = u8(3);
  seq.normals = u8(3);
  seq.depth = u8(1);
  seq.roughness = u8(1);
  seq.metallic = torch::zeros({count, 1, h, w}, torch::kUInt8);
  std::atomic<int64_t> next{0};
  std::mutex mutex;
  absl::Status first_error;
  auto work = [&] {
    for (int64_t i = next++; i < count; i = next++) {
      absl::StatusOr<DatasetFrame> frame = dataset.ReadFrame(static_cast<size_t>(i));
      if (!frame.ok()) {
        std::lock_guard<std::mutex> lock(mutex);
        if (first_error.ok()) first_error = frame.status();
        return;
      }
      seq.final_image[i].copy_(
          ResizeToTensor(*frame->final_image, 3, options.width, options.height));
      seq.basecolor[i].copy_(ResizeToTensor(frame->basecolor, 3, options.width, options.height));
      seq.normals[i].copy_(ResizeToTensor(frame->normals, 3, options.width, options.height));
      seq.depth[i].copy_(ResizeToTensor(frame->depth, 1, options.width, options.height));
      seq.roughness[i].copy_(ResizeToTensor(frame->roughness, 1, options.width, options.height));
      if (frame->metallic) {
        seq.metallic[i].copy_(ResizeToTensor(*frame->metallic, 1, options.width, options.height));
      }
    }
  };
  std::vector<std::thread> pool;
  for (int t = 0; t < std::max(1, options.decode_threads); ++t) pool.emplace_back(work);
  for (std::thread& t : pool) t.join();
  return first_error;
}

}  // namespace

int64_t TrainingData::frame_count() const {
  int64_t total = 0;
  for (const TrainingSequence& s : sequences) total += s.size();
  return total;
}

torch::Tensor ResizeToTensor(const AnyImage& image, int channels, int width, int height) {
  torch::NoGradGuard no_grad;
  const fd::client::Image8 u8 = fd::client::ToUint8(image);
  // HWC bytes -> [1, C, H, W]
  torch::Tensor t = torch::from_blob(const_cast<uint8_t*>(u8.pixels.data()),
                                     {u8.height, u8.width, u8.channels}, torch::kUInt8)
                        .permute({2, 0, 1})
                        .unsqueeze(0);
  if (u8.channels != channels) {
    // The Dataset already converts to the buffer's channel count; keep the
    // first channels for anything else.
    t = t.slice(1, 0, channels);
  }
  if (u8.width == width && u8.height == height) return t[0].contiguous().clone();
  namespace F = torch::nn::functional;
  torch::Tensor resized =
      F::interpolate(t.to(torch::kFloat32), F::InterpolateFuncOptions()
                                                .size(std::vector<int64_t>{height, width})
                                                .mode(torch::kBilinear)
                                                .align_corners(false)
                                                .antialias(true));
  return resized.round().clamp(0, 255).to(torch::kUInt8)[0].contiguous();
}

absl::StatusOr<std::vector<std::string>> ExpandSequenceFolders(
    const std::vector<std::string>& dirs) {
  std::vector<std::string> out;
  for (const std::string& dir : dirs) {
    std::error_code ec;
    if (!fs::is_directory(dir, ec)) {
      return absl::NotFoundError(absl::StrCat("--data folder does not exist: ", dir));
    }
    const std::vector<std::string> children = fd::client::ListSequenceFolders(dir);
    const bool is_sequence = fs::is_directory(fs::path(dir) / "BaseColor", ec) ||
                             fs::is_directory(fs::path(dir) / "FinalImage", ec);
    if (!is_sequence && !children.empty()) {
      for (const std::string& child : children) out.push_back((fs::path(dir) / child).string());
    } else {
      out.push_back(dir);
    }
  }
  return out;
}

absl::StatusOr<TrainingData> LoadTrainingData(const std::vector<std::string>& dirs,
                                              const TrainingDataOptions& options) {
  if (dirs.empty()) return absl::InvalidArgumentError("no --data folder given");
  if (options.width <= 0 || options.height <= 0 || options.width % 8 != 0 ||
      options.height % 8 != 0) {
    return absl::InvalidArgumentError(absl::StrCat("training resolution ", options.width, "x",
                                                   options.height,
                                                   " must be positive multiples of 8"));
  }
  absl::StatusOr<std::vector<std::string>> folders = ExpandSequenceFolders(dirs);
  if (!folders.ok()) return folders.status();
  TrainingData data;
  data.width = options.width;
  data.height = options.height;
  fd::client::DatasetOptions dataset_options;
  dataset_options.require_final_image = true;  // the training target
  dataset_options.exr_values = options.exr_values;
  for (const std::string& folder : *folders) {
    absl::StatusOr<Dataset> dataset = Dataset::Open(folder, dataset_options);
    if (!dataset.ok()) return dataset.status();
    const int64_t count = static_cast<int64_t>(dataset->frames().size());
    if (count == 0) {
      return absl::InvalidArgumentError(absl::StrCat("sequence ", folder, " has no frames"));
    }
    if (count <= options.max_offset) {
      return absl::InvalidArgumentError(absl::StrCat(
          "sequence ", folder, " has ", count, " frame(s); the temporal offsets up to +-",
          options.max_offset, " need at least ", options.max_offset + 1));
    }
    TrainingSequence seq;
    seq.dir = folder;
    for (const fd::client::FrameFiles& f : dataset->frames()) seq.frame_numbers.push_back(f.index);
    if (absl::Status decoded = DecodeSequence(*dataset, options, seq); !decoded.ok()) {
      return decoded;
    }
    data.sequences.push_back(std::move(seq));
  }
  if (data.frame_count() == 0) return absl::InvalidArgumentError("the dataset is empty");
  return data;
}

}  // namespace fd::trainer

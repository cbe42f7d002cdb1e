// The training frames of one environment: one or more G-buffer sequences in
// the authors' dataset layout (FinalImage/ BaseColor/ Normals/ Depth/
// Roughness/ Metallic/, PNG or EXR, read by fd::client_io's Dataset), decoded
// once and resized to the training resolution, held in memory as uint8
// tensors (what the authors' GBufferDataset gets from PIL).
//
// Departure from the authors' GBufferDataset: frames are resized once, when
// loading, with an antialiased bilinear filter (they resize every sample with
// LANCZOS to 512 after the noise injection); noise injection, sky fill and
// irradiance then run at the training resolution (sample_builder.h).
//
// Thread-safety: immutable after Load; any number of threads may read.
#ifndef FD_TRAINER_TRAINING_DATA_H_
#define FD_TRAINER_TRAINING_DATA_H_

#include <torch/types.h>

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "client_sdk/dataset.h"

namespace fd::trainer {

// One camera path, frames in the dataset's increasing frame-number order.
// Every tensor is uint8 [T, C, H, W] on the CPU.
struct TrainingSequence {
  std::string dir;
  std::vector<int64_t> frame_numbers;  // the files' numbers, T of them
  torch::Tensor final_image;           // [T, 3, H, W]
  torch::Tensor basecolor;             // [T, 3, H, W] RAW (not sky filled)
  torch::Tensor normals;               // [T, 3, H, W]
  torch::Tensor depth;                 // [T, 1, H, W]
  torch::Tensor roughness;             // [T, 1, H, W]
  torch::Tensor metallic;              // [T, 1, H, W]; zeros when the dataset has none

  int64_t size() const { return static_cast<int64_t>(frame_numbers.size()); }
};

struct TrainingDataOptions {
  int width = 64;  // training resolution (multiples of 8)
  int height = 64;
  // The largest |temporal offset| (the authors' max_prev_frames, 2): every
  // sequence needs more frames than this.
  int max_offset = 2;
  fd::client::ExrValues exr_values = fd::client::ExrValues::kWire;
  int decode_threads = 2;
};

struct TrainingData {
  std::vector<TrainingSequence> sequences;
  int width = 0;
  int height = 0;

  int64_t frame_count() const;
};

// The sequence folders of the --data arguments: a folder with buffer folders
// (or multi-layer EXRs) is one sequence; a folder of sequence folders (the
// authors' hierarchical layout) gives each of them.
// NOT_FOUND for a folder that does not exist.
absl::StatusOr<std::vector<std::string>> ExpandSequenceFolders(
    const std::vector<std::string>& dirs);

// Reads, validates and resizes every sequence of `dirs` (each a sequence
// folder or a folder of them). Errors, each naming the file or folder:
// INVALID_ARGUMENT for no folders, an empty dataset, a bad size, mismatched
// frame numbers or image sizes between buffers, or a sequence with no more
// than max_offset frames; NOT_FOUND for a missing folder, buffer folder or
// FinalImage; DATA_LOSS for an unreadable PNG/EXR.
absl::StatusOr<TrainingData> LoadTrainingData(const std::vector<std::string>& dirs,
                                              const TrainingDataOptions& options);

// A uint8 [C, H, W] tensor of an image (any dtype, 1 or 3 channels, values in
// [0, 1] for float) resized to width x height (antialiased bilinear, rounded
// half to even). Exposed for tests.
torch::Tensor ResizeToTensor(const fd::client::AnyImage& image, int channels, int width,
                             int height);

}  // namespace fd::trainer

#endif  // FD_TRAINER_TRAINING_DATA_H_

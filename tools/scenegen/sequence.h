// Writing a rendered sequence in the authors' dataset layout:
//
//   OUT/FinalImage/FinalImage_0000.png  OUT/BaseColor/BaseColor_0000.png
//   OUT/Normals/Normals_0000.png        OUT/Depth/Depth_0000.png
//   OUT/Roughness/Roughness_0000.png    OUT/Metallic/Metallic_0000.png
//   OUT/scene.json                      (arguments, conventions, cameras)
//
// With EXR output the .exr files sit beside the PNGs in the same folders
// (FinalImage/FinalImage_0000.exr, ...); the reference dataset reader only
// lists .png/.jpg files, so they never confuse it.
#ifndef FD_TOOLS_SCENEGEN_SEQUENCE_H_
#define FD_TOOLS_SCENEGEN_SEQUENCE_H_

#include <cstdint>
#include <functional>
#include <string>

#include "absl/status/statusor.h"
#include "tools/scenegen/encoding.h"

namespace fd::scenegen {

enum class OutputFormat { kPng, kExr, kBoth };
// Largest frame index (file names widen beyond 4 digits past 9999).
inline constexpr int kMaxFrameIndex = 10000000;
const char* OutputFormatName(OutputFormat format);

struct GeneratorOptions {
  std::string scene = "street";
  int frames = 24;
  // Index of the first frame (files and camera poses are numbered from it),
  // so long sequences can be rendered in shards.
  int start_frame = 0;
  int width = 512;
  int height = 512;
  uint64_t seed = 0;
  OutputFormat format = OutputFormat::kPng;
  // Worker threads; 0 = all hardware threads. Does not change any output
  // byte, so it is not recorded in scene.json.
  int threads = 0;
  std::string out_dir;
};

struct GenerationStats {
  int frames = 0;
  double render_seconds = 0.0;  // ray tracing + encoding
  double write_seconds = 0.0;   // PNG/EXR compression and file writes
};

// "<Buffer>_<frame, 4+ digits>.<extension>", e.g. "Depth_0007.png".
std::string BufferFileName(Buffer buffer, int frame, const std::string& extension);
// out_dir/<Buffer>/<BufferFileName>.
std::string BufferPath(const std::string& out_dir, Buffer buffer, int frame,
                       const std::string& extension);

// Renders and writes options.frames frames (start_frame ..
// start_frame + frames - 1) plus scene.json,
// creating the folders and overwriting existing files. `progress` (optional)
// is called after each frame with the frame index. Output bytes depend only
// on scene, frames, size, seed and format.
// INVALID_ARGUMENT for bad options (unknown scene, sizes, empty out_dir),
// INTERNAL when a folder or file cannot be written.
absl::StatusOr<GenerationStats> GenerateSequence(
    const GeneratorOptions& options, const std::function<void(int)>& progress = nullptr);

// Threads actually used for `requested` (0 = hardware concurrency, >= 1).
int ResolveThreads(int requested);

}  // namespace fd::scenegen

#endif  // FD_TOOLS_SCENEGEN_SEQUENCE_H_

// Reading G-buffer sequences in the FrameDiffuser authors' dataset layout
// (their GBufferDataset.py), plus OpenEXR variants.
//
// Accepted layouts of one sequence folder DIR (first match):
//
//  1. Buffer folders: DIR/<Buffer>/<Buffer>_<digits>.<ext> ("simple naming")
//     or DIR/<Buffer>/<Seq>_<Buffer>_<digits>.<ext> ("prefix naming", one
//     <Seq> prefix per folder), with <Buffer> one of FinalImage, BaseColor,
//     Normals, Depth, Roughness, Metallic and <ext> png, jpg, jpeg or exr
//     (case-insensitive; PNG is preferred when a frame has several). One EXR
//     per buffer uses ReadExr's channel rules.
//  2. Multi-layer EXR: DIR/[<Seq>_]<digits>.exr, one file per frame whose
//     layers are named like the buffers ("BaseColor.R/G/B", "Normals.X/Y/Z"
//     or ".R/G/B", "Depth.Y" or any single channel, ...). Layer names match
//     case-insensitively; aliases: Normals = Normal = WorldNormal, Depth =
//     SceneDepth, FinalImage = the unlayered R,G,B channels.
//
// BaseColor, Normals, Depth and Roughness are required for every frame.
// Metallic and FinalImage are optional but all-or-nothing: either every frame
// has one or none does (a partial set is reported as mismatched frame
// numbers, since a missing Metallic would silently become zeros). FinalImage
// can be made required (ground truth for keyframes, videos, evaluation).
// Frames are the numbers found in BaseColor; every buffer must have exactly
// those numbers and every image the same size.
//
// Values: buffers are sent to the server as read (PNG/JPEG as uint8, EXR as
// float32), so EXR values must already use the wire encoding ([0, 1],
// normals as n * 0.5 + 0.5; see render_service.proto) unless
// ExrValues::kLinear is chosen. Colour buffers stored as gray are replicated
// to RGB and scalar buffers stored as RGB are reduced to luma, as PIL's
// convert("RGB") / convert("L") do in the authors' reader.
//
// Thread-safety: a Dataset is immutable after Open; ReadFrame may be called
// concurrently.
#ifndef FD_CLIENT_SDK_DATASET_H_
#define FD_CLIENT_SDK_DATASET_H_

#include <array>
#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "client_sdk/image.h"

namespace fd::client {

enum class Buffer { kFinalImage, kBaseColor, kNormals, kDepth, kRoughness, kMetallic };
inline constexpr int kBufferCount = 6;
inline constexpr std::array<Buffer, kBufferCount> kAllBuffers = {
    Buffer::kFinalImage, Buffer::kBaseColor, Buffer::kNormals,
    Buffer::kDepth,      Buffer::kRoughness, Buffer::kMetallic};

// Folder and file-name token: "FinalImage", "BaseColor", ...
const char* BufferName(Buffer buffer);
// 3 for FinalImage, BaseColor, Normals; 1 for the others.
int BufferChannels(Buffer buffer);

// How EXR values map to the wire encoding.
enum class ExrValues {
  // Used as stored (already [0, 1] like the PNGs).
  kWire,
  // Linear scene values, as tools/scenegen writes its EXRs: BaseColor and
  // FinalImage are clamped to [0, 1] and sRGB-encoded, Normals in [-1, 1] are
  // mapped to n * 0.5 + 0.5, Depth/Roughness/Metallic are clamped to [0, 1].
  // (scenegen's FinalImage PNG is additionally tone mapped, so its EXR does
  // not reproduce the PNG exactly.)
  kLinear,
};

struct DatasetOptions {
  // NOT_FOUND for any frame without a FinalImage.
  bool require_final_image = false;
  ExrValues exr_values = ExrValues::kWire;
  // With prefix naming and several sequences in one folder, which <Seq> to
  // read; empty = the only one (INVALID_ARGUMENT listing them otherwise).
  std::string sequence;
};

// The files of one frame; an empty path means the buffer is absent (only
// Metallic and a non-required FinalImage can be). In the multi-layer EXR
// layout every present buffer has the frame's EXR path.
struct FrameFiles {
  int64_t index = 0;
  std::array<std::string, kBufferCount> paths;
  const std::string& path(Buffer buffer) const { return paths[static_cast<int>(buffer)]; }
};

// One frame's images, converted to the buffer's channel count.
struct DatasetFrame {
  int64_t index = 0;
  std::optional<AnyImage> final_image;
  AnyImage basecolor;
  AnyImage normals;
  AnyImage depth;
  AnyImage roughness;
  std::optional<AnyImage> metallic;  // absent: all zeros (the server's default)
};

class Dataset {
 public:
  // Scans DIR and validates it from the file headers (existence of every
  // required buffer per frame, equal frame numbers and sizes) without
  // decoding pixels. NOT_FOUND naming the expected file for a missing
  // buffer or folder, INVALID_ARGUMENT naming the file for mismatched frame
  // numbers or sizes, DATA_LOSS for an unreadable file. When DIR holds
  // sequence sub-folders instead (the authors' hierarchical layout), the
  // error lists them.
  static absl::StatusOr<Dataset> Open(const std::string& dir, const DatasetOptions& options = {});

  const std::string& dir() const { return dir_; }
  // Frames in increasing index order.
  const std::vector<FrameFiles>& frames() const { return frames_; }
  int width() const { return width_; }
  int height() const { return height_; }
  bool has(Buffer buffer) const { return present_[static_cast<int>(buffer)]; }
  // "buffer folders" or "multi-layer EXR".
  bool multi_layer_exr() const { return multi_layer_; }
  // Position of frame `index` in frames(), or nullopt.
  std::optional<size_t> Find(int64_t index) const;

  // Decodes frame frames()[position]. DATA_LOSS for an unreadable file,
  // INVALID_ARGUMENT when a file changed size since Open.
  absl::StatusOr<DatasetFrame> ReadFrame(size_t position) const;
  // Decodes one buffer of one frame (e.g. FinalImage for a keyframe).
  absl::StatusOr<AnyImage> ReadBuffer(size_t position, Buffer buffer) const;

 private:
  std::string dir_;
  DatasetOptions options_;
  std::vector<FrameFiles> frames_;
  std::array<bool, kBufferCount> present_{};
  bool multi_layer_ = false;
  int width_ = 0;
  int height_ = 0;
};

// Numbered images for evaluation: DIR/FinalImage/[<Seq>_]FinalImage_<digits>.<ext>
// when DIR/FinalImage exists, else DIR/[<name>_]<digits>.<ext>, with <ext>
// png, jpg, jpeg or exr. Maps frame number -> path. NOT_FOUND when there are
// none, INVALID_ARGUMENT for several name prefixes or a duplicate number.
absl::StatusOr<std::map<int64_t, std::string>> ListFrameImages(const std::string& dir);

// Sub-folders of `root` that look like sequences (contain BaseColor/ or
// FinalImage/), sorted; for the authors' hierarchical layout.
std::vector<std::string> ListSequenceFolders(const std::string& root);

}  // namespace fd::client

#endif  // FD_CLIENT_SDK_DATASET_H_

#include "client_sdk/dataset.h"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <filesystem>
#include <functional>
#include <map>
#include <set>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "client_sdk/image_io.h"

namespace fd::client {
namespace {

namespace fs = std::filesystem;

constexpr int Slot(Buffer buffer) { return static_cast<int>(buffer); }

// Preference when a frame has several files: the authors' reader tries .png
// first, then .jpg.
int ExtensionRank(const std::string& lower_ext) {
  if (lower_ext == ".png") return 0;
  if (lower_ext == ".jpg") return 1;
  if (lower_ext == ".jpeg") return 2;
  if (lower_ext == ".exr") return 3;
  return -1;
}

bool AllDigits(std::string_view s) {
  return !s.empty() && std::all_of(s.begin(), s.end(), [](char c) { return c >= '0' && c <= '9'; });
}

// A file name split as [<prefix>_]<token>_<digits>.<ext>; token may be empty
// (multi-layer EXR frames: [<prefix>_]<digits>.exr).
struct ParsedName {
  std::string prefix;
  std::string digits;
  int64_t index = 0;
  int rank = 0;
};

std::optional<ParsedName> ParseName(const std::string& file_name, const std::string& token) {
  const fs::path path(file_name);
  const std::string ext = absl::AsciiStrToLower(path.extension().string());
  const int rank = ExtensionRank(ext);
  if (rank < 0) return std::nullopt;
  const std::string stem = path.stem().string();
  const size_t underscore = stem.rfind('_');
  std::string digits = underscore == std::string::npos ? stem : stem.substr(underscore + 1);
  // Indices beyond 18 digits would overflow int64; nobody has such datasets.
  if (!AllDigits(digits) || digits.size() > 18) return std::nullopt;
  std::string rest = underscore == std::string::npos ? "" : stem.substr(0, underscore);
  ParsedName parsed;
  if (token.empty()) {
    if (underscore == std::string::npos) {
      parsed.prefix = "";
    } else {
      parsed.prefix = rest;
    }
  } else {
    if (rest == token) {
      parsed.prefix = "";
    } else if (absl::EndsWith(rest, absl::StrCat("_", token))) {
      parsed.prefix = rest.substr(0, rest.size() - token.size() - 1);
    } else {
      return std::nullopt;
    }
  }
  parsed.digits = std::move(digits);
  parsed.index = std::stoll(parsed.digits);
  parsed.rank = rank;
  return parsed;
}

struct FoundFile {
  std::string path;
  std::string digits;
  int rank = 0;
};

// index -> best file, per prefix.
using FileMap = std::map<int64_t, FoundFile>;

// Lists the files of one folder that name `token`, grouped by prefix. A
// duplicate frame (same index and extension rank, e.g. _7 and _0007) is
// INVALID_ARGUMENT.
absl::StatusOr<std::map<std::string, FileMap>> ScanFolder(const fs::path& folder,
                                                          const std::string& token) {
  std::map<std::string, FileMap> by_prefix;
  std::error_code ec;
  std::vector<fs::path> entries;
  for (const fs::directory_entry& entry : fs::directory_iterator(folder, ec)) {
    if (entry.is_regular_file(ec)) entries.push_back(entry.path());
  }
  if (ec) {
    return absl::DataLossError(absl::StrCat("cannot list ", folder.string(), ": ", ec.message()));
  }
  std::sort(entries.begin(), entries.end());
  for (const fs::path& path : entries) {
    std::optional<ParsedName> parsed = ParseName(path.filename().string(), token);
    if (!parsed) continue;
    FileMap& files = by_prefix[parsed->prefix];
    auto [it, inserted] = files.try_emplace(parsed->index);
    if (!inserted) {
      if (it->second.rank == parsed->rank) {
        return absl::InvalidArgumentError(absl::StrCat("duplicate frame ", parsed->index, ": ",
                                                       it->second.path, " and ", path.string()));
      }
      if (it->second.rank < parsed->rank) continue;
    }
    it->second = FoundFile{path.string(), parsed->digits, parsed->rank};
  }
  return by_prefix;
}

absl::StatusOr<std::string> PickPrefix(const std::map<std::string, FileMap>& by_prefix,
                                       const std::string& wanted, const std::string& where) {
  if (!wanted.empty()) {
    if (by_prefix.count(wanted) == 0) {
      std::vector<std::string> names;
      for (const auto& [prefix, files] : by_prefix)
        names.push_back(prefix.empty() ? "(none)" : prefix);
      return absl::NotFoundError(absl::StrCat("no sequence '", wanted, "' in ", where,
                                              " (found: ", absl::StrJoin(names, ", "), ")"));
    }
    return wanted;
  }
  if (by_prefix.size() > 1) {
    std::vector<std::string> names;
    for (const auto& [prefix, files] : by_prefix)
      names.push_back(prefix.empty() ? "(none)" : prefix);
    return absl::InvalidArgumentError(absl::StrCat(where, " holds several sequences (prefixes ",
                                                   absl::StrJoin(names, ", "),
                                                   "); choose one (--sequence NAME)"));
  }
  return by_prefix.begin()->first;
}

std::string ExpectedName(const std::string& prefix, const std::string& token,
                         const std::string& digits) {
  std::string name = prefix.empty() ? "" : prefix + "_";
  if (!token.empty()) absl::StrAppend(&name, token, "_");
  absl::StrAppend(&name, digits);
  return name;
}

std::string FrameRange(const std::vector<int64_t>& indices) {
  if (indices.empty()) return "none";
  return absl::StrCat(indices.front(), "..", indices.back(), " (", indices.size(), " frames)");
}

bool IsRequired(Buffer buffer, const DatasetOptions& options) {
  switch (buffer) {
    case Buffer::kBaseColor:
    case Buffer::kNormals:
    case Buffer::kDepth:
    case Buffer::kRoughness:
      return true;
    case Buffer::kFinalImage:
      return options.require_final_image;
    case Buffer::kMetallic:
      return false;
  }
  return false;
}

// Checks one buffer's frame numbers against BaseColor's and fills `frames`.
// `found` is empty when the folder/layer is absent altogether.
// `expected(i)` says where frame base_indices[i]'s file was looked for.
absl::Status MatchFrames(Buffer buffer, const FileMap& found, bool folder_exists,
                         const DatasetOptions& options, const std::string& dir,
                         const std::vector<int64_t>& base_indices,
                         const std::function<std::string(size_t)>& expected,
                         std::vector<FrameFiles>* frames, bool* present) {
  const std::string name(BufferName(buffer));
  const bool required = IsRequired(buffer, options);
  const std::string folder = (fs::path(dir) / name).string();
  if (found.empty()) {
    if (required) {
      if (!folder_exists) {
        return absl::NotFoundError(
            absl::StrCat("missing buffer folder ", folder,
                         " (required: ", "BaseColor, Normals, Depth, Roughness",
                         options.require_final_image ? ", FinalImage" : "", ")"));
      }
      return absl::NotFoundError(absl::StrCat("missing ", name, " buffer for frame ",
                                              base_indices.front(), ": expected ", expected(0)));
    }
    *present = false;
    return absl::OkStatus();
  }
  *present = true;
  std::vector<size_t> missing;
  for (size_t i = 0; i < base_indices.size(); ++i) {
    auto it = found.find(base_indices[i]);
    if (it == found.end()) {
      missing.push_back(i);
    } else {
      (*frames)[i].paths[Slot(buffer)] = it->second.path;
    }
  }
  std::vector<int64_t> extra;
  for (const auto& [index, file] : found) {
    if (!std::binary_search(base_indices.begin(), base_indices.end(), index))
      extra.push_back(index);
  }
  std::vector<int64_t> own;
  for (const auto& [index, file] : found) own.push_back(index);
  const std::string expected_missing = missing.empty() ? "" : expected(missing.front());
  if (!extra.empty() || (!missing.empty() && !required)) {
    std::string detail;
    if (!extra.empty()) {
      detail =
          absl::StrCat(found.at(extra.front()).path, " has no BaseColor frame ", extra.front());
    } else {
      detail = absl::StrCat("frame ", base_indices[missing.front()], " has no ", name,
                            " file (expected ", expected_missing, ")");
      if (buffer == Buffer::kMetallic || buffer == Buffer::kFinalImage) {
        absl::StrAppend(&detail, "; provide ", name, " for every frame or for none");
      }
    }
    return absl::InvalidArgumentError(
        absl::StrCat("mismatched frame numbers: BaseColor has frames ", FrameRange(base_indices),
                     ", ", name, " has ", FrameRange(own), ": ", detail));
  }
  if (!missing.empty()) {
    return absl::NotFoundError(absl::StrCat("missing ", name, " buffer for frame ",
                                            base_indices[missing.front()], ": expected ",
                                            expected_missing));
  }
  return absl::OkStatus();
}

// Multi-layer EXR: which layer holds `buffer` ("" = unlayered), or nullopt.
std::optional<std::string> FindLayer(const std::vector<std::string>& layers, Buffer buffer) {
  std::vector<std::string> names = {std::string(BufferName(buffer))};
  if (buffer == Buffer::kNormals) names = {"Normals", "Normal", "WorldNormal"};
  if (buffer == Buffer::kDepth) names = {"Depth", "SceneDepth"};
  for (const std::string& name : names) {
    for (const std::string& layer : layers) {
      if (absl::EqualsIgnoreCase(layer, name)) return layer;
    }
  }
  if (buffer == Buffer::kFinalImage &&
      std::find(layers.begin(), layers.end(), "") != layers.end()) {
    return std::string();
  }
  return std::nullopt;
}

float SrgbEncode(float linear) {
  const float x = std::clamp(linear, 0.0f, 1.0f);
  return x <= 0.0031308f ? 12.92f * x : 1.055f * std::pow(x, 1.0f / 2.4f) - 0.055f;
}

void ApplyLinearConvention(Buffer buffer, ImageF* image) {
  for (float& v : image->pixels) {
    switch (buffer) {
      case Buffer::kFinalImage:
      case Buffer::kBaseColor:
        v = SrgbEncode(v);
        break;
      case Buffer::kNormals:
        v = std::clamp(v * 0.5f + 0.5f, 0.0f, 1.0f);
        break;
      default:
        v = std::clamp(v, 0.0f, 1.0f);
        break;
    }
  }
}

}  // namespace

const char* BufferName(Buffer buffer) {
  switch (buffer) {
    case Buffer::kFinalImage:
      return "FinalImage";
    case Buffer::kBaseColor:
      return "BaseColor";
    case Buffer::kNormals:
      return "Normals";
    case Buffer::kDepth:
      return "Depth";
    case Buffer::kRoughness:
      return "Roughness";
    case Buffer::kMetallic:
      return "Metallic";
  }
  return "?";
}

int BufferChannels(Buffer buffer) {
  switch (buffer) {
    case Buffer::kFinalImage:
    case Buffer::kBaseColor:
    case Buffer::kNormals:
      return 3;
    default:
      return 1;
  }
}

absl::StatusOr<std::map<int64_t, std::string>> ListFrameImages(const std::string& dir) {
  std::error_code ec;
  if (!fs::is_directory(dir, ec)) return absl::NotFoundError(absl::StrCat("no such folder: ", dir));
  const fs::path final_folder = fs::path(dir) / "FinalImage";
  const bool dataset = fs::is_directory(final_folder, ec);
  const fs::path folder = dataset ? final_folder : fs::path(dir);
  absl::StatusOr<std::map<std::string, FileMap>> found =
      ScanFolder(folder, dataset ? "FinalImage" : "");
  if (!found.ok()) return found.status();
  if (found->empty()) {
    return absl::NotFoundError(
        absl::StrCat("no numbered images in ", folder.string(), " (expected names like ",
                     dataset ? "FinalImage_0000.png" : "frame_0000.png", ")"));
  }
  absl::StatusOr<std::string> prefix = PickPrefix(*found, "", folder.string());
  if (!prefix.ok()) return prefix.status();
  std::map<int64_t, std::string> frames;
  for (const auto& [index, file] : found->at(*prefix)) frames[index] = file.path;
  return frames;
}

std::vector<std::string> ListSequenceFolders(const std::string& root) {
  std::vector<std::string> sequences;
  std::error_code ec;
  for (const fs::directory_entry& entry : fs::directory_iterator(root, ec)) {
    if (!entry.is_directory(ec)) continue;
    if (fs::is_directory(entry.path() / "BaseColor", ec) ||
        fs::is_directory(entry.path() / "FinalImage", ec)) {
      sequences.push_back(entry.path().filename().string());
    }
  }
  std::sort(sequences.begin(), sequences.end());
  return sequences;
}

absl::StatusOr<Dataset> Dataset::Open(const std::string& dir, const DatasetOptions& options) {
  std::error_code ec;
  if (!fs::is_directory(dir, ec)) {
    return absl::NotFoundError(absl::StrCat("input folder does not exist: ", dir));
  }
  Dataset dataset;
  dataset.dir_ = dir;
  dataset.options_ = options;

  std::map<Buffer, FileMap> found;
  std::map<Buffer, bool> folder_exists;
  std::string prefix;
  const fs::path base_folder = fs::path(dir) / "BaseColor";
  if (fs::is_directory(base_folder, ec)) {
    // Layout 1: buffer folders.
    absl::StatusOr<std::map<std::string, FileMap>> base = ScanFolder(base_folder, "BaseColor");
    if (!base.ok()) return base.status();
    if (base->empty()) {
      return absl::NotFoundError(absl::StrCat(
          "no frames: ", base_folder.string(),
          " has no files named [<Seq>_]BaseColor_<digits>.png (or .jpg, .jpeg, .exr)"));
    }
    absl::StatusOr<std::string> picked = PickPrefix(*base, options.sequence, base_folder.string());
    if (!picked.ok()) return picked.status();
    prefix = *picked;
    for (Buffer buffer : kAllBuffers) {
      const fs::path folder = fs::path(dir) / std::string(BufferName(buffer));
      folder_exists[buffer] = fs::is_directory(folder, ec);
      if (!folder_exists[buffer]) continue;
      absl::StatusOr<std::map<std::string, FileMap>> files =
          buffer == Buffer::kBaseColor ? base : ScanFolder(folder, BufferName(buffer));
      if (!files.ok()) return files.status();
      auto it = files->find(prefix);
      if (it != files->end()) found[buffer] = std::move(it->second);
    }
  } else {
    // Layout 2: one multi-layer EXR per frame.
    absl::StatusOr<std::map<std::string, FileMap>> exrs = ScanFolder(dir, "");
    if (!exrs.ok()) return exrs.status();
    for (auto it = exrs->begin(); it != exrs->end();) {
      // Only .exr files form frames in this layout.
      FileMap& files = it->second;
      for (auto f = files.begin(); f != files.end();) {
        f = f->second.rank == 3 ? std::next(f) : files.erase(f);
      }
      it = files.empty() ? exrs->erase(it) : std::next(it);
    }
    if (exrs->empty()) {
      const std::vector<std::string> sequences = ListSequenceFolders(dir);
      if (!sequences.empty()) {
        return absl::InvalidArgumentError(
            absl::StrCat(dir, " holds sequence folders (", absl::StrJoin(sequences, ", "),
                         ") rather than one sequence; pass one of them, e.g. ",
                         (fs::path(dir) / sequences.front()).string()));
      }
      return absl::NotFoundError(absl::StrCat(
          "no frames in ", dir, ": expected a BaseColor/ folder (",
          (base_folder / "BaseColor_0000.png").string(), ", ...) or multi-layer EXR frames (",
          (fs::path(dir) / "Frame_0000.exr").string(), ")"));
    }
    absl::StatusOr<std::string> picked = PickPrefix(*exrs, options.sequence, dir);
    if (!picked.ok()) return picked.status();
    prefix = *picked;
    dataset.multi_layer_ = true;
    const FileMap& files = exrs->at(prefix);
    for (const auto& [index, file] : files) {
      absl::StatusOr<std::vector<std::string>> layers = ListExrLayers(file.path);
      if (!layers.ok()) return layers.status();
      for (Buffer buffer : kAllBuffers) {
        if (FindLayer(*layers, buffer).has_value()) {
          found[buffer][index] = file;
        } else if (IsRequired(buffer, options)) {
          return absl::NotFoundError(
              absl::StrCat("missing ", BufferName(buffer), " buffer for frame ", index, ": ",
                           file.path, " has no ", BufferName(buffer),
                           " layer (layers: ", absl::StrJoin(*layers, ", "), ")"));
        }
      }
    }
    for (Buffer buffer : kAllBuffers) folder_exists[buffer] = true;
  }

  // Frames are BaseColor's numbers; every other buffer must match them.
  const FileMap& base_files = found[Buffer::kBaseColor];
  std::vector<int64_t> base_indices;
  std::vector<std::string> base_digits;
  for (const auto& [index, file] : base_files) {
    base_indices.push_back(index);
    base_digits.push_back(file.digits);
  }
  dataset.frames_.resize(base_indices.size());
  for (size_t i = 0; i < base_indices.size(); ++i) dataset.frames_[i].index = base_indices[i];
  for (Buffer buffer : kAllBuffers) {
    bool present = false;
    const std::string name(BufferName(buffer));
    auto expected = [&](size_t i) {
      if (dataset.multi_layer_) {
        return absl::StrCat("a ", name, " layer in ", base_files.at(base_indices[i]).path);
      }
      return absl::StrCat(
          (fs::path(dir) / name / ExpectedName(prefix, name, base_digits[i])).string(),
          ".png (or .jpg, .jpeg, .exr)");
    };
    if (absl::Status s = MatchFrames(buffer, found[buffer], folder_exists[buffer], options, dir,
                                     base_indices, expected, &dataset.frames_, &present);
        !s.ok()) {
      return s;
    }
    dataset.present_[Slot(buffer)] = present;
  }

  // Sizes, from the headers only (for multi-layer EXRs also checks that each
  // buffer's layer has usable channels).
  auto info_of = [&](const std::string& path, Buffer buffer) -> absl::StatusOr<ImageFileInfo> {
    if (!dataset.multi_layer_) return ReadImageInfo(path);
    absl::StatusOr<std::vector<std::string>> layers = ListExrLayers(path);
    if (!layers.ok()) return layers.status();
    std::optional<std::string> layer = FindLayer(*layers, buffer);
    if (!layer)
      return absl::NotFoundError(absl::StrCat(path, " has no ", BufferName(buffer), " layer"));
    return ReadExrLayerInfo(path, *layer);
  };
  const std::string& reference = dataset.frames_.front().path(Buffer::kBaseColor);
  absl::StatusOr<ImageFileInfo> reference_info = info_of(reference, Buffer::kBaseColor);
  if (!reference_info.ok()) return reference_info.status();
  dataset.width_ = reference_info->width;
  dataset.height_ = reference_info->height;
  std::set<std::string> checked;
  for (const FrameFiles& frame : dataset.frames_) {
    for (Buffer buffer : kAllBuffers) {
      const std::string& path = frame.path(buffer);
      const std::string key = dataset.multi_layer_ ? path + "#" + BufferName(buffer) : path;
      if (path.empty() || !checked.insert(key).second) continue;
      absl::StatusOr<ImageFileInfo> info = info_of(path, buffer);
      if (!info.ok()) return info.status();
      if (info->width != dataset.width_ || info->height != dataset.height_) {
        return absl::InvalidArgumentError(
            absl::StrCat("size mismatch: ", path, " is ", info->width, "x", info->height, ", but ",
                         reference, " is ", dataset.width_, "x", dataset.height_));
      }
    }
  }
  return dataset;
}

std::optional<size_t> Dataset::Find(int64_t index) const {
  auto it = std::lower_bound(frames_.begin(), frames_.end(), index,
                             [](const FrameFiles& f, int64_t i) { return f.index < i; });
  if (it == frames_.end() || it->index != index) return std::nullopt;
  return static_cast<size_t>(it - frames_.begin());
}

absl::StatusOr<AnyImage> Dataset::ReadBuffer(size_t position, Buffer buffer) const {
  if (position >= frames_.size()) {
    return absl::OutOfRangeError(
        absl::StrCat("frame position ", position, " >= ", frames_.size(), " frames"));
  }
  const FrameFiles& files = frames_[position];
  const std::string& path = files.path(buffer);
  if (path.empty()) {
    return absl::NotFoundError(
        absl::StrCat("frame ", files.index, " has no ", BufferName(buffer), " buffer in ", dir_));
  }
  AnyImage image;
  if (multi_layer_) {
    absl::StatusOr<std::vector<std::string>> layers = ListExrLayers(path);
    if (!layers.ok()) return layers.status();
    std::optional<std::string> layer = FindLayer(*layers, buffer);
    if (!layer) {
      return absl::NotFoundError(absl::StrCat(path, " has no ", BufferName(buffer), " layer"));
    }
    absl::StatusOr<ImageF> read = ReadExrLayer(path, *layer);
    if (!read.ok()) return read.status();
    image = std::move(*read);
  } else {
    absl::StatusOr<AnyImage> read = ReadImage(path);
    if (!read.ok()) return read.status();
    image = std::move(*read);
  }
  if (auto* f = std::get_if<ImageF>(&image);
      f != nullptr && options_.exr_values == ExrValues::kLinear) {
    ApplyLinearConvention(buffer, f);
  }
  if (WidthOf(image) != width_ || HeightOf(image) != height_) {
    return absl::InvalidArgumentError(absl::StrCat("size mismatch: ", path, " is ", WidthOf(image),
                                                   "x", HeightOf(image), ", the dataset is ",
                                                   width_, "x", height_));
  }
  return ToChannels(image, BufferChannels(buffer));
}

absl::StatusOr<DatasetFrame> Dataset::ReadFrame(size_t position) const {
  if (position >= frames_.size()) {
    return absl::OutOfRangeError(
        absl::StrCat("frame position ", position, " >= ", frames_.size(), " frames"));
  }
  DatasetFrame frame;
  frame.index = frames_[position].index;
  auto read = [&](Buffer buffer, AnyImage* out) -> absl::Status {
    absl::StatusOr<AnyImage> image = ReadBuffer(position, buffer);
    if (!image.ok()) return image.status();
    *out = std::move(*image);
    return absl::OkStatus();
  };
  for (auto [buffer, out] :
       {std::pair{Buffer::kBaseColor, &frame.basecolor},
        std::pair{Buffer::kNormals, &frame.normals}, std::pair{Buffer::kDepth, &frame.depth},
        std::pair{Buffer::kRoughness, &frame.roughness}}) {
    if (absl::Status s = read(buffer, out); !s.ok()) return s;
  }
  for (auto [buffer, out] : {std::pair{Buffer::kFinalImage, &frame.final_image},
                             std::pair{Buffer::kMetallic, &frame.metallic}}) {
    if (!has(buffer)) continue;
    AnyImage image;
    if (absl::Status s = read(buffer, &image); !s.ok()) return s;
    *out = std::move(image);
  }
  return frame;
}

}  // namespace fd::client

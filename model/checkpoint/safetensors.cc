// safetensors reader/writer; see safetensors.h and the format description in
// huggingface/safetensors (safetensors/src/tensor.rs, which this validation
// follows: header length, JSON object, dtype/shape/data_offsets per tensor,
// offsets inside the data section, sized to the shape, non-overlapping).
#include "model/checkpoint/safetensors.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <torch/torch.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <limits>
#include <nlohmann/json.hpp>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/string_view.h"
#include "base/status_macros.h"
#include "model/runtime/torch_call.h"

namespace fd::model {
namespace {

static_assert(sizeof(void*) == 8, "safetensors offsets need a 64-bit address space");

// Note: Debian's abseil has its own absl::string_view (not std::string_view),
// so std::string_view arguments are converted before absl::StrCat.

// The format is little endian; so are all hosts we build for (x86-64, aarch64).
#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ != __ORDER_LITTLE_ENDIAN__
#error "safetensors.cc assumes a little-endian host"
#endif

// A header larger than this is refused, as the reference implementation does
// (100 MB), so a corrupt length cannot make us parse gigabytes.
constexpr uint64_t kMaxHeaderBytes = 100'000'000;

struct DtypeEntry {
  const char* name;
  torch::ScalarType type;
  size_t element_size;
};

constexpr DtypeEntry kDtypes[] = {
    {"F64", torch::kFloat64, 8},   {"F32", torch::kFloat32, 4}, {"F16", torch::kFloat16, 2},
    {"BF16", torch::kBFloat16, 2}, {"I64", torch::kInt64, 8},   {"I32", torch::kInt32, 4},
    {"I16", torch::kInt16, 2},     {"I8", torch::kInt8, 1},     {"U8", torch::kUInt8, 1},
    {"BOOL", torch::kBool, 1},
};

const DtypeEntry* FindDtype(std::string_view name) {
  for (const DtypeEntry& entry : kDtypes) {
    if (name == entry.name) return &entry;
  }
  return nullptr;
}

const DtypeEntry* FindDtype(torch::ScalarType type) {
  for (const DtypeEntry& entry : kDtypes) {
    if (type == entry.type) return &entry;
  }
  return nullptr;
}

std::string SupportedDtypeNames() {
  std::vector<std::string> names;
  for (const DtypeEntry& entry : kDtypes) names.emplace_back(entry.name);
  return absl::StrJoin(names, ", ");
}

std::string ShapeString(const std::vector<int64_t>& shape) {
  return absl::StrCat("[", absl::StrJoin(shape, ", "), "]");
}

absl::Status Corrupt(const std::string& path, absl::string_view what) {
  return absl::InvalidArgumentError(absl::StrCat("safetensors file '", path, "': ", what));
}

absl::Status CorruptTensor(const std::string& path, absl::string_view tensor,
                           absl::string_view what) {
  return absl::InvalidArgumentError(
      absl::StrCat("safetensors file '", path, "', tensor '", tensor, "': ", what));
}

// Reads a non-negative JSON integer; false for any other JSON value
// (floats, negatives, strings...).
bool ReadUnsigned(const nlohmann::json& value, uint64_t* out) {
  if (value.is_number_unsigned()) {
    *out = value.get<uint64_t>();
    return true;
  }
  if (value.is_number_integer()) {
    const int64_t signed_value = value.get<int64_t>();
    if (signed_value < 0) return false;
    *out = static_cast<uint64_t>(signed_value);
    return true;
  }
  return false;
}

// Parses and validates one tensor entry of the header.
absl::StatusOr<SafetensorsFile::TensorInfo> ParseTensorInfo(const std::string& path,
                                                            const std::string& name,
                                                            const nlohmann::json& entry,
                                                            uint64_t data_size) {
  if (!entry.is_object()) {
    return CorruptTensor(path, name,
                         absl::StrCat("header entry is not a JSON object but ", entry.type_name()));
  }
  SafetensorsFile::TensorInfo info;

  const auto dtype_it = entry.find("dtype");
  if (dtype_it == entry.end()) return CorruptTensor(path, name, "missing 'dtype'");
  if (!dtype_it->is_string()) return CorruptTensor(path, name, "'dtype' is not a string");
  info.dtype = dtype_it->get<std::string>();
  const DtypeEntry* dtype = FindDtype(info.dtype);
  if (dtype == nullptr) {
    return CorruptTensor(path, name,
                         absl::StrCat("unknown or unsupported dtype '", info.dtype,
                                      "' (supported: ", SupportedDtypeNames(), ")"));
  }
  info.scalar_type = dtype->type;

  const auto shape_it = entry.find("shape");
  if (shape_it == entry.end()) return CorruptTensor(path, name, "missing 'shape'");
  if (!shape_it->is_array()) return CorruptTensor(path, name, "'shape' is not an array");
  // numel * element size, guarding against overflow of a hostile shape.
  uint64_t byte_size = dtype->element_size;
  bool overflow = false;
  for (const nlohmann::json& dim_json : *shape_it) {
    if (dim_json.is_number_integer() && !dim_json.is_number_unsigned() &&
        dim_json.get<int64_t>() < 0) {
      return CorruptTensor(
          path, name,
          absl::StrCat("negative dimension ", dim_json.dump(), " in shape ", shape_it->dump()));
    }
    uint64_t dim = 0;
    if (!ReadUnsigned(dim_json, &dim) ||
        dim > static_cast<uint64_t>(std::numeric_limits<int64_t>::max())) {
      return CorruptTensor(
          path, name, absl::StrCat("shape ", shape_it->dump(), " has a non-integer dimension"));
    }
    info.shape.push_back(static_cast<int64_t>(dim));
    if (dim != 0 && byte_size > std::numeric_limits<uint64_t>::max() / dim) overflow = true;
    byte_size *= dim;
  }
  if (overflow) {
    bool has_zero = std::find(info.shape.begin(), info.shape.end(), 0) != info.shape.end();
    if (!has_zero) {
      return CorruptTensor(path, name,
                           absl::StrCat("shape ", ShapeString(info.shape), " is too large"));
    }
    byte_size = 0;
  }

  const auto offsets_it = entry.find("data_offsets");
  if (offsets_it == entry.end()) return CorruptTensor(path, name, "missing 'data_offsets'");
  if (!offsets_it->is_array() || offsets_it->size() != 2 ||
      !ReadUnsigned((*offsets_it)[0], &info.begin) || !ReadUnsigned((*offsets_it)[1], &info.end)) {
    return CorruptTensor(
        path, name,
        absl::StrCat("'data_offsets' must be two non-negative integers, got ", offsets_it->dump()));
  }
  if (info.begin > info.end) {
    return CorruptTensor(
        path, name,
        absl::StrCat("data_offsets begin ", info.begin, " is greater than end ", info.end));
  }
  if (info.end > data_size) {
    return CorruptTensor(path, name,
                         absl::StrCat("data_offsets [", info.begin, ", ", info.end,
                                      "] out of range: the data section has ", data_size,
                                      " bytes (file truncated?)"));
  }
  if (info.end - info.begin != byte_size) {
    return CorruptTensor(
        path, name,
        absl::StrCat("data_offsets [", info.begin, ", ", info.end, "] span ", info.end - info.begin,
                     " bytes but dtype ", info.dtype, " with shape ", ShapeString(info.shape),
                     " needs ", byte_size, " bytes"));
  }
  return info;
}

// The header length read from the first 8 bytes of a `file_size`-byte file:
// inside the file and under the reference implementation's limit.
absl::Status CheckHeaderSize(const std::string& path, uint64_t header_size, uint64_t file_size) {
  if (header_size > file_size - 8) {
    return Corrupt(path, absl::StrCat("header length ", header_size, " runs past the end of the ",
                                      file_size, "-byte file (truncated or not safetensors)"));
  }
  if (header_size > kMaxHeaderBytes) {
    return Corrupt(path, absl::StrCat("header length ", header_size, " exceeds the limit of ",
                                      kMaxHeaderBytes, " bytes"));
  }
  return absl::OkStatus();
}

// Reads exactly `size` bytes at `offset` (pread: no shared file position, so
// concurrent Get() calls need no lock). A file that ends early, because it
// was truncated after Open() validated its size, is DATA_LOSS naming
// `tensor` (or the header when empty).
absl::Status ReadAt(int fd, const std::string& path, void* out, uint64_t size, uint64_t offset,
                    absl::string_view tensor = {}) {
  auto where = [&] {
    return absl::StrCat("safetensors file '", path, "'",
                        tensor.empty() ? "" : absl::StrCat(", tensor '", tensor, "'"));
  };
  auto* dst = static_cast<char*>(out);
  uint64_t done = 0;
  while (done < size) {
    const ssize_t got = ::pread(fd, dst + done, size - done, static_cast<off_t>(offset + done));
    if (got < 0) {
      if (errno == EINTR) continue;
      return absl::InternalError(absl::StrCat("reading ", where(), ": ", std::strerror(errno)));
    }
    if (got == 0) {
      return absl::DataLossError(
          absl::StrCat(where(), ": the file ended at byte ", offset + done, " but ", offset + size,
                       " were expected (was it truncated or replaced while being loaded?)"));
    }
    done += static_cast<uint64_t>(got);
  }
  return absl::OkStatus();
}

absl::Status WriteAll(std::FILE* file, const void* data, size_t size, const std::string& path) {
  if (size == 0) return absl::OkStatus();
  if (std::fwrite(data, 1, size, file) != size) {
    return absl::InternalError(
        absl::StrCat("writing safetensors file '", path, "': ", std::strerror(errno)));
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<std::unique_ptr<SafetensorsFile>> SafetensorsFile::Open(const std::string& path) {
  std::unique_ptr<SafetensorsFile> file(new SafetensorsFile());
  file->path_ = path;
  file->fd_ = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (file->fd_ < 0) {
    const int error = errno;
    const std::string message =
        absl::StrCat("cannot open safetensors file '", path, "': ", std::strerror(error));
    if (error == ENOENT || error == ENOTDIR) return absl::NotFoundError(message);
    if (error == EACCES) return absl::PermissionDeniedError(message);
    return absl::InternalError(message);
  }
  struct stat st {};
  if (::fstat(file->fd_, &st) != 0) {
    return absl::InternalError(
        absl::StrCat("cannot stat safetensors file '", path, "': ", std::strerror(errno)));
  }
  if (!S_ISREG(st.st_mode)) return Corrupt(path, "not a regular file");
  const uint64_t file_size = static_cast<uint64_t>(st.st_size);
  if (file_size < 8) {
    return Corrupt(
        path, absl::StrCat("file is ", file_size, " bytes, shorter than the 8-byte header length"));
  }
  uint64_t header_size = 0;  // little endian
  FD_RETURN_IF_ERROR(ReadAt(file->fd_, path, &header_size, sizeof(header_size), 0));
  FD_RETURN_IF_ERROR(CheckHeaderSize(path, header_size, file_size));
  std::string header(header_size, '\0');
  FD_RETURN_IF_ERROR(ReadAt(file->fd_, path, header.data(), header_size, 8));
  FD_RETURN_IF_ERROR(file->ParseHeader(header.data(), header_size, file_size));
  return file;
}

absl::StatusOr<std::unique_ptr<SafetensorsFile>> SafetensorsFile::FromBuffer(
    const std::string& name, const uint8_t* data, size_t size) {
  if (size < 8) {
    return Corrupt(name,
                   absl::StrCat("file is ", size, " bytes, shorter than the 8-byte header length"));
  }
  std::unique_ptr<SafetensorsFile> file(new SafetensorsFile());
  file->path_ = name;
  file->buffer_ = data;
  uint64_t header_size = 0;
  std::memcpy(&header_size, data, sizeof(header_size));  // little endian
  FD_RETURN_IF_ERROR(CheckHeaderSize(name, header_size, size));
  FD_RETURN_IF_ERROR(file->ParseHeader(reinterpret_cast<const char*>(data + 8), header_size, size));
  return file;
}

absl::Status SafetensorsFile::ParseHeader(const char* header_begin, uint64_t header_size,
                                          uint64_t file_size) {
  const std::string& path = path_;
  SafetensorsFile* file = this;
  file->data_begin_ = 8 + header_size;
  const uint64_t data_size = file_size - file->data_begin_;

  nlohmann::json header = nlohmann::json::parse(header_begin, header_begin + header_size,
                                                /*cb=*/nullptr, /*allow_exceptions=*/false);
  if (header.is_discarded()) return Corrupt(path, "header is not valid JSON");
  if (!header.is_object()) {
    return Corrupt(path,
                   absl::StrCat("header is a JSON ", header.type_name(), ", expected an object"));
  }

  for (const auto& [name, entry] : header.items()) {
    if (name == "__metadata__") {
      if (!entry.is_object()) return Corrupt(path, "'__metadata__' is not a JSON object");
      for (const auto& [meta_key, meta_value] : entry.items()) {
        if (!meta_value.is_string()) {
          return Corrupt(path,
                         absl::StrCat("'__metadata__' value of '", meta_key, "' is not a string"));
        }
        file->metadata_.emplace(meta_key, meta_value.get<std::string>());
      }
      continue;
    }
    FD_ASSIGN_OR_RETURN(TensorInfo info, ParseTensorInfo(path, name, entry, data_size));
    file->tensors_.emplace(name, std::move(info));
  }

  // Overlap check: sorted by begin, each non-empty tensor must start at or
  // after the end of every earlier one.
  std::vector<std::pair<const std::string*, const TensorInfo*>> by_offset;
  for (const auto& [name, info] : file->tensors_) {
    if (info.end > info.begin) by_offset.emplace_back(&name, &info);
  }
  std::sort(by_offset.begin(), by_offset.end(), [](const auto& a, const auto& b) {
    return std::tie(a.second->begin, a.second->end) < std::tie(b.second->begin, b.second->end);
  });
  for (size_t i = 1; i < by_offset.size(); ++i) {
    const auto& [prev_name, prev] = by_offset[i - 1];
    const auto& [name, info] = by_offset[i];
    if (info->begin < prev->end) {
      return CorruptTensor(
          path, *name,
          absl::StrCat("data_offsets [", info->begin, ", ", info->end, "] overlap tensor '",
                       *prev_name, "' at [", prev->begin, ", ", prev->end, "]"));
    }
  }
  return absl::OkStatus();
}

SafetensorsFile::~SafetensorsFile() {
  if (fd_ >= 0) ::close(fd_);
}

std::vector<std::string> SafetensorsFile::Keys() const {
  std::vector<std::string> keys;
  keys.reserve(tensors_.size());
  for (const auto& [name, info] : tensors_) keys.push_back(name);
  return keys;
}

bool SafetensorsFile::Contains(std::string_view key) const {
  return tensors_.find(key) != tensors_.end();
}

absl::StatusOr<SafetensorsFile::TensorInfo> SafetensorsFile::Info(std::string_view key) const {
  const auto it = tensors_.find(key);
  if (it == tensors_.end()) {
    return absl::NotFoundError(absl::StrCat("safetensors file '", path_, "' has no tensor '",
                                            absl::string_view(key.data(), key.size()), "'"));
  }
  return it->second;
}

absl::StatusOr<torch::Tensor> SafetensorsFile::Get(std::string_view key) const {
  FD_ASSIGN_OR_RETURN(const TensorInfo info, Info(key));
  const DtypeEntry* dtype = FindDtype(info.dtype);  // validated in Open()
  return TorchCall("SafetensorsFile::Get", [&]() -> absl::StatusOr<torch::Tensor> {
    torch::Tensor tensor = torch::empty(info.shape, torch::TensorOptions().dtype(dtype->type));
    const size_t bytes = info.end - info.begin;
    if (bytes == 0) return tensor;
    if (buffer_ != nullptr) {
      std::memcpy(tensor.data_ptr(), buffer_ + data_begin_ + info.begin, bytes);
      return tensor;
    }
    FD_RETURN_IF_ERROR(ReadAt(fd_, path_, tensor.data_ptr(), bytes, data_begin_ + info.begin,
                              absl::string_view(key.data(), key.size())));
    return tensor;
  });
}

absl::StatusOr<std::map<std::string, torch::Tensor>> LoadSafetensors(const std::string& path) {
  FD_ASSIGN_OR_RETURN(std::unique_ptr<SafetensorsFile> file, SafetensorsFile::Open(path));
  std::map<std::string, torch::Tensor> tensors;
  for (const std::string& key : file->Keys()) {
    FD_ASSIGN_OR_RETURN(torch::Tensor tensor, file->Get(key));
    tensors.emplace(key, std::move(tensor));
  }
  return tensors;
}

absl::Status SaveSafetensors(const std::string& path,
                             const std::map<std::string, torch::Tensor>& tensors,
                             const std::map<std::string, std::string>& metadata) {
  return TorchCall("SaveSafetensors", [&]() -> absl::Status {
    // Header: "__metadata__" first, then the tensors in key order, data laid
    // out in the same order (as huggingface/safetensors serialize() does).
    nlohmann::ordered_json header = nlohmann::ordered_json::object();
    if (!metadata.empty()) {
      nlohmann::ordered_json meta = nlohmann::ordered_json::object();
      for (const auto& [key, value] : metadata) meta[key] = value;
      header["__metadata__"] = std::move(meta);
    }
    std::vector<torch::Tensor> cpu_tensors;
    cpu_tensors.reserve(tensors.size());
    uint64_t offset = 0;
    for (const auto& [name, tensor] : tensors) {
      if (name == "__metadata__") {
        return absl::InvalidArgumentError(absl::StrCat(
            "SaveSafetensors '", path, "': '__metadata__' is reserved as a tensor name"));
      }
      if (!tensor.defined()) {
        return absl::InvalidArgumentError(
            absl::StrCat("SaveSafetensors '", path, "', tensor '", name, "': undefined tensor"));
      }
      const DtypeEntry* dtype = FindDtype(tensor.scalar_type());
      if (dtype == nullptr) {
        return absl::InvalidArgumentError(absl::StrCat(
            "SaveSafetensors '", path, "', tensor '", name, "': unsupported dtype ",
            c10::toString(tensor.scalar_type()), " (supported: ", SupportedDtypeNames(), ")"));
      }
      torch::Tensor cpu = tensor.detach().to(torch::kCPU).contiguous();
      const uint64_t bytes = static_cast<uint64_t>(cpu.numel()) * dtype->element_size;
      header[name] = {{"dtype", dtype->name},
                      {"shape", cpu.sizes().vec()},
                      {"data_offsets", {offset, offset + bytes}}};
      offset += bytes;
      cpu_tensors.push_back(std::move(cpu));
    }
    std::string header_text = header.dump();
    // Pad with spaces so the data section starts 8-byte aligned.
    header_text.append((8 - header_text.size() % 8) % 8, ' ');
    const uint64_t header_size = header_text.size();

    // Unique per process and call, so concurrent saves never share a temp file.
    static std::atomic<uint64_t> save_counter{0};
    const std::string temp_path =
        absl::StrCat(path, ".tmp.", ::getpid(), ".", save_counter.fetch_add(1));
    std::FILE* out = std::fopen(temp_path.c_str(), "wb");
    if (out == nullptr) {
      return absl::InternalError(
          absl::StrCat("cannot create '", temp_path, "': ", std::strerror(errno)));
    }
    absl::Status status = WriteAll(out, &header_size, sizeof(header_size), temp_path);
    if (status.ok()) status = WriteAll(out, header_text.data(), header_text.size(), temp_path);
    for (const torch::Tensor& cpu : cpu_tensors) {
      if (!status.ok()) break;
      status = WriteAll(out, cpu.data_ptr(), cpu.numel() * cpu.element_size(), temp_path);
    }
    // Durable before the rename: a crash leaves the old file or the new one,
    // never a torn one (the trainer's checkpoints rely on this).
    if (status.ok() && (std::fflush(out) != 0 || ::fsync(::fileno(out)) != 0)) {
      status = absl::InternalError(
          absl::StrCat("cannot flush '", temp_path, "': ", std::strerror(errno)));
    }
    if (std::fclose(out) != 0 && status.ok()) {
      status =
          absl::InternalError(absl::StrCat("closing '", temp_path, "': ", std::strerror(errno)));
    }
    if (status.ok() && std::rename(temp_path.c_str(), path.c_str()) != 0) {
      status = absl::InternalError(
          absl::StrCat("cannot rename '", temp_path, "' to '", path, "': ", std::strerror(errno)));
    }
    if (!status.ok()) std::remove(temp_path.c_str());
    return status;
  });
}

}  // namespace fd::model

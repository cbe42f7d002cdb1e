// Reader and writer for the safetensors format
// (https://github.com/huggingface/safetensors): 8-byte little-endian header
// length N, N bytes of JSON {name: {dtype, shape, data_offsets:[begin,end]},
// "__metadata__": {str: str}}, then the raw little-endian tensor bytes.
//
// Supported dtypes: F32, F16, BF16, F64, I64, I32, I8, U8, BOOL (the goldens
// store uint8 images); any other dtype is rejected by name.
// Every error message names the file and, where it applies, the tensor.
#ifndef FD_MODEL_CHECKPOINT_SAFETENSORS_H_
#define FD_MODEL_CHECKPOINT_SAFETENSORS_H_

#include <torch/types.h>

#include <cstdint>
#include <map>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace fd::model {

// A validated .safetensors file.
//
// Ownership: owns an open file descriptor (Open) or borrows the bytes
// (FromBuffer); tensors returned by Get() are independent copies and stay
// valid after the file is destroyed. Open() reads the header and Get() reads
// each tensor with pread(2), not through a memory mapping: a file that another
// process truncates after Open() (a `cp` over a checkpoint during a reload)
// fails the Get() with DATA_LOSS instead of ending the process with SIGBUS.
// Thread-safety: immutable after Open(); all const methods may be called
// concurrently.
class SafetensorsFile {
 public:
  struct TensorInfo {
    std::string dtype;                                // e.g. "F32", "F16", "BF16", "I64", "U8"
    torch::ScalarType scalar_type = torch::kFloat32;  // the same as a LibTorch dtype
    std::vector<int64_t> shape;                       // may be empty (a scalar)
    uint64_t begin = 0;                               // byte offsets relative to the data section
    uint64_t end = 0;
  };

  // Maps and validates `path`: header length within the file, JSON well
  // formed, known dtypes, offsets in range, sized to the shape, not
  // overlapping. Errors: NOT_FOUND (no such file), INVALID_ARGUMENT (any
  // corruption; the message names the file and the tensor), INTERNAL (I/O).
  static absl::StatusOr<std::unique_ptr<SafetensorsFile>> Open(const std::string& path);

  // The same validation for a file held in memory (e.g. compiled into a
  // binary): `data` (`size` bytes) is borrowed and must outlive the object;
  // `name` stands for the path in messages. INVALID_ARGUMENT on corruption.
  static absl::StatusOr<std::unique_ptr<SafetensorsFile>> FromBuffer(const std::string& name,
                                                                     const uint8_t* data,
                                                                     size_t size);

  ~SafetensorsFile();
  SafetensorsFile(const SafetensorsFile&) = delete;
  SafetensorsFile& operator=(const SafetensorsFile&) = delete;

  const std::string& path() const { return path_; }
  // Tensor names, sorted.
  std::vector<std::string> Keys() const;
  bool Contains(std::string_view key) const;
  // NOT_FOUND if absent.
  absl::StatusOr<TensorInfo> Info(std::string_view key) const;
  // The `__metadata__` map (empty when absent).
  const std::map<std::string, std::string>& metadata() const { return metadata_; }

  // A CPU tensor (contiguous, owning copy) in the file's dtype.
  // NOT_FOUND if the key is absent; DATA_LOSS if the file became shorter
  // than its header says after Open(); INTERNAL on a read error.
  absl::StatusOr<torch::Tensor> Get(std::string_view key) const;

 private:
  SafetensorsFile() = default;
  // Validates `header_size` bytes of JSON header (which followed the 8-byte
  // length in a file of `file_size` bytes) and fills tensors_/metadata_.
  absl::Status ParseHeader(const char* header, uint64_t header_size, uint64_t file_size);

  std::string path_;
  int fd_ = -1;                      // Open(): read with pread, closed on destruction
  const uint8_t* buffer_ = nullptr;  // FromBuffer(): the borrowed bytes
  size_t data_begin_ = 0;            // 8 + header length
  std::map<std::string, TensorInfo, std::less<>> tensors_;
  std::map<std::string, std::string> metadata_;
};

// Loads every tensor of a file (owning CPU copies), keyed by name.
absl::StatusOr<std::map<std::string, torch::Tensor>> LoadSafetensors(const std::string& path);

// Writes `tensors` (any device; stored contiguous, little endian, in their own
// dtype, which must be one of the supported ones) with optional
// metadata. Writes to a temporary file and renames it into place.
// Errors: INVALID_ARGUMENT (unsupported dtype), INTERNAL (I/O).
absl::Status SaveSafetensors(const std::string& path,
                             const std::map<std::string, torch::Tensor>& tensors,
                             const std::map<std::string, std::string>& metadata = {});

}  // namespace fd::model

#endif  // FD_MODEL_CHECKPOINT_SAFETENSORS_H_

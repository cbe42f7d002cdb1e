// Where the checkpoint loaders read an environment's files from: the file
// system (DiskFiles, the default) or files held in memory (MemoryFiles: an
// environment compiled into a binary is loaded straight from its bytes,
// never written to a temporary folder first).
//
// Paths are what the loaders build ("<dir>/unet/config.json"); a
// MemoryFiles serves the paths under its root.
#ifndef FD_MODEL_CHECKPOINT_FILE_SOURCE_H_
#define FD_MODEL_CHECKPOINT_FILE_SOURCE_H_

#include <map>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "model/checkpoint/safetensors.h"

namespace fd::model {

// Thread-safety: implementations are immutable; every method may be called
// concurrently.
class FileSource {
 public:
  virtual ~FileSource() = default;

  virtual bool IsFile(const std::string& path) const = 0;
  virtual bool IsDirectory(const std::string& path) const = 0;
  // Names of the entries (files and folders) directly in `dir`, sorted;
  // empty when it is not a folder.
  virtual std::vector<std::string> List(const std::string& dir) const = 0;
  // A whole file. NOT_FOUND if missing, INTERNAL on read errors.
  virtual absl::StatusOr<std::string> ReadText(const std::string& path) const = 0;
  // A validated safetensors file (SafetensorsFile::Open / FromBuffer errors).
  virtual absl::StatusOr<std::unique_ptr<SafetensorsFile>> OpenSafetensors(
      const std::string& path) const = 0;
};

// The file system.
const FileSource& DiskFiles();

// Files in memory. Ownership: the bytes are borrowed and must outlive the
// object (e.g. a binary's read-only data).
class MemoryFiles final : public FileSource {
 public:
  // `files`: '/'-separated path relative to `root` -> bytes. `root` names
  // the folder in paths and messages (e.g. "<embedded>/default").
  MemoryFiles(std::string root, std::map<std::string, std::string_view> files);

  const std::string& root() const { return root_; }

  bool IsFile(const std::string& path) const override;
  bool IsDirectory(const std::string& path) const override;
  std::vector<std::string> List(const std::string& dir) const override;
  absl::StatusOr<std::string> ReadText(const std::string& path) const override;
  absl::StatusOr<std::unique_ptr<SafetensorsFile>> OpenSafetensors(
      const std::string& path) const override;

 private:
  // `path` relative to the root ("" for the root itself); nullopt-like
  // false when it is outside the root.
  bool Relative(const std::string& path, std::string* relative) const;

  const std::string root_;
  const std::map<std::string, std::string_view> files_;
};

}  // namespace fd::model

#endif  // FD_MODEL_CHECKPOINT_FILE_SOURCE_H_

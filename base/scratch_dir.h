// A temporary folder that removes itself (the random test environment is
// written to one and loaded from it; tests make their data in one).
// Move-only; not thread-safe.
#ifndef FD_BASE_SCRATCH_DIR_H_
#define FD_BASE_SCRATCH_DIR_H_

#include <stdlib.h>

#include <filesystem>
#include <string>
#include <system_error>

#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"

namespace fd {

class ScratchDir {
 public:
  // A fresh folder named like <root>/<prefix>XXXXXX (the system temporary
  // folder when root is empty). INTERNAL when it cannot be created.
  static absl::StatusOr<ScratchDir> Create(const std::string& root, const std::string& prefix) {
    std::error_code ec;
    const std::filesystem::path base =
        root.empty() ? std::filesystem::temp_directory_path(ec) : std::filesystem::path(root);
    if (ec) return absl::InternalError(absl::StrCat("no temporary folder: ", ec.message()));
    std::string pattern = (base / (prefix + "XXXXXX")).string();
    if (mkdtemp(pattern.data()) == nullptr) {
      return absl::InternalError(absl::StrCat("cannot create a folder like ", pattern));
    }
    return ScratchDir(pattern);
  }
  ScratchDir(ScratchDir&& other) noexcept : path_(std::move(other.path_)) { other.path_.clear(); }
  ScratchDir& operator=(ScratchDir&&) = delete;
  ScratchDir(const ScratchDir&) = delete;
  ~ScratchDir() {
    std::error_code ec;
    if (!path_.empty()) std::filesystem::remove_all(path_, ec);
  }
  const std::string& path() const { return path_; }

 private:
  explicit ScratchDir(std::string path) : path_(std::move(path)) {}
  std::string path_;
};

}  // namespace fd

#endif  // FD_BASE_SCRATCH_DIR_H_

#include "model/checkpoint/file_source.h"

#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>
#include <system_error>
#include <utility>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/string_view.h"

namespace fd::model {
namespace {

namespace fs = std::filesystem;

class DiskFileSource final : public FileSource {
 public:
  bool IsFile(const std::string& path) const override {
    std::error_code error;
    return fs::is_regular_file(path, error);
  }
  bool IsDirectory(const std::string& path) const override {
    std::error_code error;
    return fs::is_directory(path, error);
  }
  std::vector<std::string> List(const std::string& dir) const override {
    std::set<std::string> names;
    std::error_code error;
    for (fs::directory_iterator it(dir, error), end; !error && it != end; it.increment(error)) {
      names.insert(it->path().filename().string());
    }
    return {names.begin(), names.end()};
  }
  absl::StatusOr<std::string> ReadText(const std::string& path) const override {
    std::ifstream in(path, std::ios::binary);
    if (!in) return absl::NotFoundError(absl::StrCat("cannot open ", path));
    std::ostringstream text;
    text << in.rdbuf();
    if (in.bad()) return absl::InternalError(absl::StrCat("cannot read ", path));
    return text.str();
  }
  absl::StatusOr<std::unique_ptr<SafetensorsFile>> OpenSafetensors(
      const std::string& path) const override {
    return SafetensorsFile::Open(path);
  }
};

}  // namespace

const FileSource& DiskFiles() {
  static const DiskFileSource* const files = new DiskFileSource();
  return *files;
}

MemoryFiles::MemoryFiles(std::string root, std::map<std::string, std::string_view> files)
    : root_(std::move(root)), files_(std::move(files)) {}

bool MemoryFiles::Relative(const std::string& path, std::string* relative) const {
  if (path == root_) {
    relative->clear();
    return true;
  }
  if (path.size() <= root_.size() + 1 || path.compare(0, root_.size(), root_) != 0 ||
      path[root_.size()] != '/') {
    return false;
  }
  *relative = fs::path(path.substr(root_.size() + 1)).lexically_normal().generic_string();
  return true;
}

bool MemoryFiles::IsFile(const std::string& path) const {
  std::string relative;
  return Relative(path, &relative) && files_.count(relative) > 0;
}

bool MemoryFiles::IsDirectory(const std::string& path) const {
  std::string relative;
  if (!Relative(path, &relative)) return false;
  if (relative.empty()) return true;
  const std::string prefix = relative + "/";
  auto it = files_.lower_bound(prefix);
  return it != files_.end() && it->first.compare(0, prefix.size(), prefix) == 0;
}

std::vector<std::string> MemoryFiles::List(const std::string& dir) const {
  std::string relative;
  if (!Relative(dir, &relative)) return {};
  const std::string prefix = relative.empty() ? "" : relative + "/";
  std::set<std::string> names;
  for (auto it = files_.lower_bound(prefix);
       it != files_.end() && it->first.compare(0, prefix.size(), prefix) == 0; ++it) {
    const std::string rest = it->first.substr(prefix.size());
    names.insert(rest.substr(0, rest.find('/')));
  }
  return {names.begin(), names.end()};
}

absl::StatusOr<std::string> MemoryFiles::ReadText(const std::string& path) const {
  std::string relative;
  if (!Relative(path, &relative)) return absl::NotFoundError(absl::StrCat("cannot open ", path));
  auto it = files_.find(relative);
  if (it == files_.end()) return absl::NotFoundError(absl::StrCat("cannot open ", path));
  return std::string(it->second);
}

absl::StatusOr<std::unique_ptr<SafetensorsFile>> MemoryFiles::OpenSafetensors(
    const std::string& path) const {
  std::string relative;
  auto it = Relative(path, &relative) ? files_.find(relative) : files_.end();
  if (it == files_.end()) {
    return absl::NotFoundError(absl::StrCat("cannot open safetensors file '", path, "'"));
  }
  return SafetensorsFile::FromBuffer(path, reinterpret_cast<const uint8_t*>(it->second.data()),
                                     it->second.size());
}

}  // namespace fd::model

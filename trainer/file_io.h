// Small file helpers the trainer's sources share.
#ifndef FD_TRAINER_FILE_IO_H_
#define FD_TRAINER_FILE_IO_H_

#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <system_error>

#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"

namespace fd::trainer {

// The whole file. NOT_FOUND naming it when it cannot be read.
inline absl::StatusOr<std::string> ReadTextFile(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::NotFoundError(absl::StrCat("cannot read ", path));
  std::stringstream buffer;
  buffer << in.rdbuf();
  return buffer.str();
}

inline bool PathExists(const std::filesystem::path& path) {
  std::error_code ec;
  return std::filesystem::exists(path, ec);
}

}  // namespace fd::trainer

#endif  // FD_TRAINER_FILE_IO_H_

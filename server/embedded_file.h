// A file compiled into a binary by fd_embed_directory (cmake/FdEmbedFiles.cmake).
#ifndef FD_SERVER_EMBEDDED_FILE_H_
#define FD_SERVER_EMBEDDED_FILE_H_

#include <cstddef>
#include <string_view>
#include <vector>

namespace fd::embedded {

struct File {
  const char* path;   // relative to the embedded folder, '/'-separated
  const char* begin;  // the bytes, in the binary's read-only data
  const char* end;

  std::string_view bytes() const { return {begin, static_cast<size_t>(end - begin)}; }
};

}  // namespace fd::embedded

#endif  // FD_SERVER_EMBEDDED_FILE_H_

#include "client_sdk/cli/video.h"

#include <fcntl.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <filesystem>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "client_sdk/raster.h"

namespace fd::client::cli {

std::string FindExecutable(const std::string& name) {
  const char* path = std::getenv("PATH");
  if (path == nullptr) return "";
  for (absl::string_view dir : absl::StrSplit(path, ':')) {
    if (dir.empty()) continue;
    const std::string candidate = absl::StrCat(dir, "/", name);
    if (::access(candidate.c_str(), X_OK) == 0 && std::filesystem::is_regular_file(candidate)) {
      return candidate;
    }
  }
  return "";
}

VideoWriter::VideoWriter(pid_t pid, int fd, int width, int height, std::string path)
    : pid_(pid), fd_(fd), width_(width), height_(height), path_(std::move(path)) {}

absl::StatusOr<std::unique_ptr<VideoWriter>> VideoWriter::Open(const std::string& ffmpeg,
                                                               const std::string& path, int width,
                                                               int height, int fps) {
  ::signal(SIGPIPE, SIG_IGN);
  int fds[2];
  if (::pipe(fds) != 0) {
    return absl::InternalError(absl::StrCat("pipe: ", std::strerror(errno)));
  }
  const std::string size = absl::StrCat(width, "x", height);
  const std::string rate = absl::StrCat(fps);
  // yuv420p needs even sizes; H.264 at visually lossless quality.
  std::vector<std::string> args = {ffmpeg,
                                   "-hide_banner",
                                   "-loglevel",
                                   "error",
                                   "-y",
                                   "-f",
                                   "rawvideo",
                                   "-pix_fmt",
                                   "rgb24",
                                   "-s",
                                   size,
                                   "-r",
                                   rate,
                                   "-i",
                                   "-",
                                   "-vf",
                                   "pad=ceil(iw/2)*2:ceil(ih/2)*2",
                                   "-c:v",
                                   "libx264",
                                   "-crf",
                                   "18",
                                   "-pix_fmt",
                                   "yuv420p",
                                   path};
  std::vector<char*> argv;
  for (std::string& arg : args) argv.push_back(arg.data());
  argv.push_back(nullptr);
  const pid_t pid = ::fork();
  if (pid < 0) {
    ::close(fds[0]);
    ::close(fds[1]);
    return absl::InternalError(absl::StrCat("fork: ", std::strerror(errno)));
  }
  if (pid == 0) {
    ::dup2(fds[0], STDIN_FILENO);
    ::close(fds[0]);
    ::close(fds[1]);
    ::execv(argv[0], argv.data());
    ::_exit(127);
  }
  ::close(fds[0]);
  ::fcntl(fds[1], F_SETFD, FD_CLOEXEC);
  return std::unique_ptr<VideoWriter>(new VideoWriter(pid, fds[1], width, height, path));
}

VideoWriter::~VideoWriter() { (void)Close(); }

absl::Status VideoWriter::Write(const Image8& rgb) {
  if (fd_ < 0) return absl::FailedPreconditionError("video already closed");
  if (rgb.width != width_ || rgb.height != height_ || rgb.channels != 3) {
    return absl::InvalidArgumentError(absl::StrCat("video frame is ", rgb.width, "x", rgb.height,
                                                   "x", rgb.channels, ", expected ", width_, "x",
                                                   height_, "x3"));
  }
  const char* data = reinterpret_cast<const char*>(rgb.pixels.data());
  size_t left = rgb.pixels.size();
  while (left > 0) {
    const ssize_t written = ::write(fd_, data, left);
    if (written < 0) {
      if (errno == EINTR) continue;
      return absl::InternalError(absl::StrCat("ffmpeg stopped reading frames for ", path_, ": ",
                                              std::strerror(errno), " (see its messages above)"));
    }
    data += written;
    left -= static_cast<size_t>(written);
  }
  return absl::OkStatus();
}

absl::Status VideoWriter::Close() {
  if (fd_ < 0) return absl::OkStatus();
  ::close(fd_);
  fd_ = -1;
  int status = 0;
  while (::waitpid(pid_, &status, 0) < 0) {
    if (errno != EINTR) return absl::InternalError(absl::StrCat("waitpid: ", std::strerror(errno)));
  }
  if (!WIFEXITED(status) || WEXITSTATUS(status) != 0) {
    return absl::InternalError(
        absl::StrCat("ffmpeg failed writing ", path_,
                     WIFEXITED(status) ? absl::StrCat(" (exit status ", WEXITSTATUS(status), ")")
                                       : std::string(" (killed by a signal)")));
  }
  return absl::OkStatus();
}

Image8 SideBySide(const std::vector<const Image8*>& panels, const std::vector<std::string>& labels,
                  int width, int height) {
  Image8 out(width * static_cast<int>(panels.size()), height, 3);
  Canvas canvas(&out);
  for (size_t i = 0; i < panels.size(); ++i) {
    const Image8* panel = panels[i];
    const int x0 = static_cast<int>(i) * width;
    if (panel != nullptr && panel->width == width && panel->height == height &&
        (panel->channels == 1 || panel->channels == 3)) {
      for (int y = 0; y < height; ++y) {
        for (int x = 0; x < width; ++x) {
          for (int c = 0; c < 3; ++c) {
            out.at(x0 + x, y, c) = panel->at(x, y, panel->channels == 1 ? 0 : c);
          }
        }
      }
    }
    if (i < labels.size() && height >= 48) {
      const int scale = height >= 256 ? 2 : 1;
      const int w = Canvas::TextWidth(labels[i], scale);
      canvas.FillRect(x0, 0, x0 + w + 6 * scale, Canvas::TextHeight(scale) + 6 * scale, {0, 0, 0});
      canvas.Text(x0 + 3 * scale, 3 * scale, labels[i], {255, 255, 255}, scale);
    }
  }
  return out;
}

}  // namespace fd::client::cli

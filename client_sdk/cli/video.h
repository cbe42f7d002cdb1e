// Videos for `framediffuser-client render --video`: raw RGB frames piped
// into an ffmpeg child process (H.264, yuv420p), and the side-by-side panel
// composition (ground truth | ours | basecolor | irradiance).
#ifndef FD_CLIENT_SDK_CLI_VIDEO_H_
#define FD_CLIENT_SDK_CLI_VIDEO_H_

#include <sys/types.h>

#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "client_sdk/image.h"

namespace fd::client::cli {

// Full path of `name` found on $PATH, or "" when absent.
std::string FindExecutable(const std::string& name);

class VideoWriter {
 public:
  // Starts `ffmpeg` writing `path` from width x height RGB frames at `fps`
  // (odd sizes are padded to even). Ignores SIGPIPE for the process so a
  // dying ffmpeg is an error, not a crash. INTERNAL when it cannot start.
  static absl::StatusOr<std::unique_ptr<VideoWriter>> Open(const std::string& ffmpeg,
                                                           const std::string& path, int width,
                                                           int height, int fps);
  ~VideoWriter();

  // One frame: RGB, width x height. INTERNAL when ffmpeg stopped reading.
  absl::Status Write(const Image8& rgb);
  // Ends the stream and waits for ffmpeg; INTERNAL when it failed.
  absl::Status Close();

 private:
  VideoWriter(pid_t pid, int fd, int width, int height, std::string path);

  pid_t pid_;
  int fd_;
  const int width_;
  const int height_;
  const std::string path_;
};

// Panels side by side, each width x height: RGB as is, gray replicated, and
// an empty (or wrongly sized) panel black. A label is drawn in the top-left
// corner of each panel when the panel is at least 48 pixels tall.
Image8 SideBySide(const std::vector<const Image8*>& panels, const std::vector<std::string>& labels,
                  int width, int height);

}  // namespace fd::client::cli

#endif  // FD_CLIENT_SDK_CLI_VIDEO_H_

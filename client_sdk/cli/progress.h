// Render progress for framediffuser-client: a live bar redrawn in place on a
// terminal ("[=====>    ] 12/100  frame 11  3.2 fps  ETA 0:27"), plain lines
// otherwise (one per frame for short runs, about 20 for long ones, so logs
// stay readable). Thread-safe.
#ifndef FD_CLIENT_SDK_CLI_PROGRESS_H_
#define FD_CLIENT_SDK_CLI_PROGRESS_H_

#include <chrono>
#include <cstdint>
#include <cstdio>
#include <mutex>
#include <string>

namespace fd::client::cli {

// "m:ss" or "h:mm:ss"; "--:--" for a negative or non-finite value.
std::string FormatDuration(double seconds);
// The bar line without the leading "\r": bar of `width` cells, counts, the
// last frame number, frames per second and the ETA.
std::string FormatProgressBar(int done, int total, int64_t frame, double fps, double eta_seconds,
                              int width = 30);

class ProgressReporter {
 public:
  // `out` is not owned; `tty` selects the live bar.
  ProgressReporter(std::FILE* out, int total, bool tty);

  // One more frame finished (frame number `frame`).
  void FrameDone(int64_t frame);
  // A message on its own line, without garbling the bar.
  void Message(const std::string& line);
  // Ends the bar line.
  void Finish();

  double elapsed_seconds() const;
  int done() const;

 private:
  void DrawLocked(int64_t frame);

  std::FILE* const out_;
  const int total_;
  const bool tty_;
  const std::chrono::steady_clock::time_point start_;
  mutable std::mutex mu_;
  int done_ = 0;
  bool bar_drawn_ = false;
};

}  // namespace fd::client::cli

#endif  // FD_CLIENT_SDK_CLI_PROGRESS_H_

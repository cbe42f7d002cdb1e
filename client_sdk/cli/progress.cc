#include "client_sdk/cli/progress.h"

#include <algorithm>
#include <cmath>

#include "absl/strings/str_format.h"

namespace fd::client::cli {

std::string FormatDuration(double seconds) {
  if (!std::isfinite(seconds) || seconds < 0) return "--:--";
  const int64_t total = static_cast<int64_t>(std::llround(seconds));
  const int64_t h = total / 3600, m = (total / 60) % 60, s = total % 60;
  if (h > 0) return absl::StrFormat("%d:%02d:%02d", h, m, s);
  return absl::StrFormat("%d:%02d", m, s);
}

std::string FormatProgressBar(int done, int total, int64_t frame, double fps, double eta_seconds,
                              int width) {
  const double fraction = total > 0 ? std::clamp(double(done) / total, 0.0, 1.0) : 0.0;
  const int filled = static_cast<int>(fraction * width);
  std::string bar(width, ' ');
  for (int i = 0; i < filled; ++i) bar[i] = '=';
  if (filled > 0 && filled < width) bar[filled - 1] = '>';  // the head of a running bar
  return absl::StrFormat("[%s] %d/%d  frame %d  %.2f fps  ETA %s", bar, done, total, frame, fps,
                         FormatDuration(eta_seconds));
}

ProgressReporter::ProgressReporter(std::FILE* out, int total, bool tty)
    : out_(out), total_(total), tty_(tty), start_(std::chrono::steady_clock::now()) {}

double ProgressReporter::elapsed_seconds() const {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
}

int ProgressReporter::done() const {
  std::lock_guard<std::mutex> lock(mu_);
  return done_;
}

void ProgressReporter::FrameDone(int64_t frame) {
  std::lock_guard<std::mutex> lock(mu_);
  ++done_;
  DrawLocked(frame);
}

void ProgressReporter::DrawLocked(int64_t frame) {
  const double elapsed = elapsed_seconds();
  const double fps = elapsed > 0 ? done_ / elapsed : 0.0;
  const double eta = fps > 0 ? (total_ - done_) / fps : -1.0;
  if (tty_) {
    std::fprintf(out_, "\r%s\033[K", FormatProgressBar(done_, total_, frame, fps, eta).c_str());
    bar_drawn_ = true;
  } else {
    const int every = std::max(1, total_ / 20);
    if (done_ % every != 0 && done_ != total_ && done_ != 1) return;
    std::fprintf(out_, "progress: %d/%d frames (frame %lld), %.2f fps, ETA %s\n", done_, total_,
                 static_cast<long long>(frame), fps, FormatDuration(eta).c_str());
  }
  std::fflush(out_);
}

void ProgressReporter::Message(const std::string& line) {
  std::lock_guard<std::mutex> lock(mu_);
  if (tty_ && bar_drawn_) std::fprintf(out_, "\r\033[K");
  std::fprintf(out_, "%s\n", line.c_str());
  bar_drawn_ = false;
  std::fflush(out_);
}

void ProgressReporter::Finish() {
  std::lock_guard<std::mutex> lock(mu_);
  if (tty_ && bar_drawn_) std::fprintf(out_, "\n");
  bar_drawn_ = false;
  std::fflush(out_);
}

}  // namespace fd::client::cli

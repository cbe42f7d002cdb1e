// framediffuser-train: trains a FrameDiffuser environment; see cli.cc for
// the flags and trainer.h for what each stage does.
#include <unistd.h>

#include <csignal>
#include <cstdio>
#include <string>
#include <vector>

#include "model/runtime/cpu_runtime.h"
#include "trainer/cli.h"
#include "trainer/trainer.h"

namespace {

volatile std::sig_atomic_t g_stop = 0;

void OnSignal(int) { g_stop = 1; }

constexpr int kExitUsage = 2;
constexpr int kExitInterrupted = 130;

}  // namespace

int main(int argc, char** argv) {
  fd::model::UseBoundedOpenMpSpin(argv);
  const std::vector<std::string> args(argv + 1, argv + argc);
  absl::StatusOr<fd::trainer::ParsedArgs> parsed = fd::trainer::ParseTrainArgs(args);
  if (!parsed.ok()) {
    std::fprintf(stderr, "framediffuser-train: %s\n",
                 std::string(parsed.status().message()).c_str());
    std::fprintf(stderr, "run framediffuser-train --help for the flags\n");
    return kExitUsage;
  }
  if (parsed->help) {
    std::fputs(fd::trainer::Usage().c_str(), stdout);
    return 0;
  }
  fd::model::UseSingleThreadedBlas();
  std::signal(SIGINT, OnSignal);
  std::signal(SIGTERM, OnSignal);
  fd::trainer::TrainerOptions options = parsed->options;
  options.command_line = "framediffuser-train";
  for (const std::string& arg : args) {
    // Shell-quoted where needed, so the recorded command can be pasted.
    const bool plain = !arg.empty() && arg.find_first_not_of(
                                           "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ"
                                           "0123456789-_./=:,+@") == std::string::npos;
    std::string quoted;
    for (char c : arg) quoted += c == '\'' ? std::string("'\\''") : std::string(1, c);
    options.command_line += " " + (plain ? arg : "'" + quoted + "'");
  }
  options.stop_requested = [] { return g_stop != 0; };
  // A log file or a CI log gets lines, not carriage-return redraws.
  if (!isatty(STDERR_FILENO)) options.progress_bar = false;
  absl::StatusOr<std::unique_ptr<fd::trainer::Trainer>> trainer =
      fd::trainer::Trainer::Create(std::move(options));
  absl::Status status = trainer.ok() ? (*trainer)->Run() : trainer.status();
  if (absl::IsCancelled(status)) {
    std::fprintf(stderr, "framediffuser-train: %s\n", std::string(status.message()).c_str());
    return kExitInterrupted;
  }
  if (!status.ok()) {
    std::fprintf(stderr, "framediffuser-train: %s\n", std::string(status.message()).c_str());
    return 1;
  }
  std::fprintf(stderr,
               "framediffuser-train: done; serve it with framediffuser-server "
               "--model_repository <folder holding %s>\n",
               parsed->options.out_dir.c_str());
  return 0;
}

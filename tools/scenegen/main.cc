// framediffuser-scenegen: writes a synthetic G-buffer sequence with a
// ray-traced ground truth in the FrameDiffuser dataset layout.
#include <cstdio>
#include <string>
#include <vector>

#include "tools/scenegen/cli.h"
#include "tools/scenegen/sequence.h"

int main(int argc, char** argv) {
  using fd::scenegen::CliCommand;
  const std::vector<std::string> args(argv + 1, argv + argc);
  absl::StatusOr<CliCommand> command = fd::scenegen::ParseCommandLine(args);
  if (!command.ok()) {
    std::fprintf(stderr, "framediffuser-scenegen: error: %s\nRun with --help for usage.\n",
                 std::string(command.status().message()).c_str());
    return fd::scenegen::kExitUsage;
  }
  if (command->action == CliCommand::Action::kHelp) {
    std::fputs(fd::scenegen::UsageText().c_str(), stdout);
    return fd::scenegen::kExitOk;
  }
  if (command->action == CliCommand::Action::kListScenes) {
    std::fputs(fd::scenegen::SceneListText().c_str(), stdout);
    return fd::scenegen::kExitOk;
  }
  const fd::scenegen::GeneratorOptions& o = command->options;
  std::fprintf(stderr, "framediffuser-scenegen: scene %s, %d frames, %dx%d, seed %llu -> %s\n",
               o.scene.c_str(), o.frames, o.width, o.height,
               static_cast<unsigned long long>(o.seed), o.out_dir.c_str());
  absl::StatusOr<fd::scenegen::GenerationStats> stats =
      fd::scenegen::GenerateSequence(o, [&](int frame) {
        // `frame` is the camera path's index (from --start); count written ones.
        const int written = frame - o.start_frame + 1;
        if (written % 10 == 0 || written == o.frames) {
          std::fprintf(stderr, "  frame %d/%d (path frame %d)\n", written, o.frames, frame);
        }
      });
  if (!stats.ok()) {
    std::fprintf(stderr, "framediffuser-scenegen: error: %s\n",
                 std::string(stats.status().message()).c_str());
    return fd::scenegen::kExitFailure;
  }
  std::fprintf(stderr, "framediffuser-scenegen: done, %.1f ms/frame render, %.1f ms/frame write\n",
               1e3 * stats->render_seconds / stats->frames,
               1e3 * stats->write_seconds / stats->frames);
  return fd::scenegen::kExitOk;
}

// Command-line parsing for framediffuser-scenegen (a small hand-written
// parser: the flag set is tiny and errors must name the offending flag).
#ifndef FD_TOOLS_SCENEGEN_CLI_H_
#define FD_TOOLS_SCENEGEN_CLI_H_

#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "tools/scenegen/sequence.h"

namespace fd::scenegen {

// Process exit codes of the tool.
inline constexpr int kExitOk = 0;
inline constexpr int kExitFailure = 1;  // generation failed (I/O)
inline constexpr int kExitUsage = 2;    // bad command line

struct CliCommand {
  enum class Action { kGenerate, kHelp, kListScenes };
  Action action = Action::kGenerate;
  GeneratorOptions options;
};

// Parses the arguments after argv[0]. Accepts "--flag value" and
// "--flag=value". INVALID_ARGUMENT with a message naming the flag for an
// unknown flag, a missing or malformed value, an unknown scene or format,
// or a missing --out.
absl::StatusOr<CliCommand> ParseCommandLine(const std::vector<std::string>& args);

// The --help text (flags, defaults, layout and encodings).
std::string UsageText();
// The --list-scenes text: one "name  description" line per preset.
std::string SceneListText();

}  // namespace fd::scenegen

#endif  // FD_TOOLS_SCENEGEN_CLI_H_

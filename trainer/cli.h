// framediffuser-train's command line: a subcommand (which stages) and flags,
// parsed into TrainerOptions. `framediffuser-train --help` prints Usage().
#ifndef FD_TRAINER_CLI_H_
#define FD_TRAINER_CLI_H_

#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "trainer/trainer_options.h"

namespace fd::trainer {

struct ParsedArgs {
  bool help = false;  // --help / -h: print Usage() and exit 0
  TrainerOptions options;
};

// args: argv[1..]. INVALID_ARGUMENT with a message naming the flag (unknown
// flag or subcommand, a missing or malformed value, a required flag absent);
// echoed values are cut to 64 characters.
absl::StatusOr<ParsedArgs> ParseTrainArgs(const std::vector<std::string>& args);

std::string Usage();

}  // namespace fd::trainer

#endif  // FD_TRAINER_CLI_H_

// The commands of framediffuser-client. Each writes its normal output to
// `out` and errors (one "error: ..." line naming the file, flag or server) to
// `err`, and returns the process exit status (cli/args.h).
#ifndef FD_CLIENT_SDK_CLI_COMMANDS_H_
#define FD_CLIENT_SDK_CLI_COMMANDS_H_

#include <cstdio>

#include "client_sdk/cli/args.h"

namespace fd::client::cli {

// Dispatches on command.kind.
int RunCommand(const Command& command, std::FILE* out, std::FILE* err);

int RunEnvs(const Command& command, std::FILE* out, std::FILE* err);
int RunHealth(const Command& command, std::FILE* out, std::FILE* err);
// `tty`: draw the live progress bar on `err` (else plain progress lines).
int RunRender(const Command& command, std::FILE* out, std::FILE* err, bool tty);
int RunEval(const Command& command, std::FILE* out, std::FILE* err);

}  // namespace fd::client::cli

#endif  // FD_CLIENT_SDK_CLI_COMMANDS_H_

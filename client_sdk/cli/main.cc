// framediffuser-client: see `framediffuser-client --help` and client_sdk/README.md.
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "client_sdk/cli/args.h"
#include "client_sdk/cli/commands.h"

int main(int argc, char** argv) {
  using fd::client::cli::kExitUsage;
  const std::vector<std::string> args(argv + 1, argv + argc);
  const char* token = std::getenv("FRAMEDIFFUSER_TOKEN");
  absl::StatusOr<fd::client::cli::Command> command =
      fd::client::cli::ParseCommandLine(args, token != nullptr ? token : "");
  if (!command.ok()) {
    std::fprintf(stderr, "error: %s\n", std::string(command.status().message()).c_str());
    std::fprintf(stderr, "run 'framediffuser-client --help' for usage\n");
    return kExitUsage;
  }
  return fd::client::cli::RunCommand(*command, stdout, stderr);
}

// Runs a command-line tool the way a user does and captures what it says,
// for the tests of framediffuser-scenegen, framediffuser-train and others.
#ifndef FD_TESTS_TESTING_RUN_TOOL_H_
#define FD_TESTS_TESTING_RUN_TOOL_H_

#include <sys/wait.h>

#include <cstdio>
#include <string>

namespace fd::testing {

struct ToolResult {
  int exit_code = -1;  // -1: did not exit normally (or could not start)
  std::string output;  // stdout and stderr
};

// `"tool" args 2>&1` through the shell; `args` is passed as written.
inline ToolResult RunTool(const std::string& tool, const std::string& args) {
  ToolResult result;
  const std::string command = "\"" + tool + "\" " + args + " 2>&1";
  FILE* pipe = popen(command.c_str(), "r");
  if (pipe == nullptr) return result;
  char buffer[4096];
  size_t n = 0;
  while ((n = fread(buffer, 1, sizeof(buffer), pipe)) > 0) result.output.append(buffer, n);
  const int status = pclose(pipe);
  result.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return result;
}

}  // namespace fd::testing

#endif  // FD_TESTS_TESTING_RUN_TOOL_H_

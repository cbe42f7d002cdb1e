// Command line of framediffuser-client (a small hand-written parser: errors
// must name the offending flag, and the flag set is small).
//
//   framediffuser-client [GLOBAL FLAGS] COMMAND [FLAGS]
// Global flags may appear anywhere; see UsageText() for the full list.
#ifndef FD_CLIENT_SDK_CLI_ARGS_H_
#define FD_CLIENT_SDK_CLI_ARGS_H_

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "client_sdk/client.h"
#include "client_sdk/dataset.h"

namespace fd::client::cli {

inline constexpr int kExitOk = 0;
inline constexpr int kExitFailure = 1;  // the command ran and failed
inline constexpr int kExitUsage = 2;    // bad command line

// A half-open range of frame numbers "A:B" (either side may be empty).
struct FrameRange {
  std::optional<int64_t> first;  // inclusive
  std::optional<int64_t> end;    // exclusive
  bool Contains(int64_t index) const {
    return (!first || index >= *first) && (!end || index < *end);
  }
};

struct ConnectionArgs {
  std::string server = "localhost:50051";
  bool tls = false;
  std::string tls_ca_file;  // PEM roots; empty = system roots
  std::string token;        // --token or $FRAMEDIFFUSER_TOKEN
  bool failover = true;
};

struct RenderArgs {
  std::string environment;
  std::string input;
  std::string output;
  std::string sequence;  // prefix selection in the input folder
  std::string keyframe_file;
  bool keyframe_from_input = false;
  FrameRange frames;
  uint32_t steps = 0;
  uint64_t seed = 0;
  Scheduler scheduler = Scheduler::kDefault;
  SkyMode sky_mode = SkyMode::kDefault;
  std::string format = "png";  // png | exr
  ExrValues exr_values = ExrValues::kWire;
  std::string video;  // .mp4 path; empty = no video
  bool side_by_side = false;
  int fps = 30;
  uint32_t max_in_flight = 2;
};

struct EvalArgs {
  std::string pred;
  std::string gt;
  std::string csv;
  std::string plot;
  FrameRange frames;
};

struct HealthArgs {
  std::string service;
};

struct Command {
  enum class Kind { kHelp, kEnvs, kHealth, kRender, kEval };
  Kind kind = Kind::kHelp;
  ConnectionArgs connection;
  RenderArgs render;
  EvalArgs eval;
  HealthArgs health;
};

// Parses argv[1..]. INVALID_ARGUMENT naming the flag for an unknown command
// or flag, a missing or malformed value, or missing required flags.
// `token_from_env` is $FRAMEDIFFUSER_TOKEN (used when --token is absent).
absl::StatusOr<Command> ParseCommandLine(const std::vector<std::string>& args,
                                         const std::string& token_from_env = "");

// "A:B", "A:", ":B" or "A" (just frame A). INVALID_ARGUMENT otherwise.
absl::StatusOr<FrameRange> ParseFrameRange(const std::string& text);

std::string UsageText();

}  // namespace fd::client::cli

#endif  // FD_CLIENT_SDK_CLI_ARGS_H_

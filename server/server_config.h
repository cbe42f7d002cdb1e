// Configuration of framediffuser-server: command-line flags and an optional
// JSON config file (`--config FILE`), both driven by ONE table of options
// (ServerConfigOptions()) so flag names, config-file keys and the --help text
// cannot drift apart.
//
// Not absl flags: Debian's LibTorch exports gflags' FLAGS_* symbols, and
// absl::ParseCommandLine exit()s on errors where we want a Status that names
// the flag.
//
// Flags:   --name=value | --name value; booleans --name, --name=true|false;
//          durations as absl::ParseDuration reads them ("250ms", "30s", "5m");
//          sizes as plain integers (bytes). '-' in a flag name reads as '_'.
// File:    a JSON object with the same names as keys; strings, integers,
//          booleans, and durations as strings ("30s").
// Order:   defaults, then the file, then the flags (flags win wherever they
//          appear relative to --config).
#ifndef FD_SERVER_SERVER_CONFIG_H_
#define FD_SERVER_SERVER_CONFIG_H_

#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/time/time.h"

// Declared in session/frame_batcher.h; opaque here so that this header does
// not pull in LibTorch.
namespace fd::session {
enum class BatchingMode;
}  // namespace fd::session

namespace fd::server {

// Value type; copyable. Thread-safety: none (a plain struct). Field comments
// are summaries; the --help text (UsageText) is the reference.
struct ServerConfig {
  std::string listen = "0.0.0.0:50051";  // host:port; port 0 = pick a free one
  std::string port_file;                 // write the bound port here (decimal + newline)
  std::string model_repository;          // empty: serve the embedded default environment
  std::string device = "cpu";            // torch device string: cpu, cuda, cuda:1
  std::string dtype = "float32";         // float32 | float16 | bfloat16
  int threads = 0;            // torch intra-op threads (per batcher worker); 0 = cores / workers
  int scheduler_workers = 0;  // per environment; each runs its own batch; 0 = auto
  bool controlnet_beside_unet = true;  // a frame may use an idle core (ControlNet || UNet down)
  std::string batching = "step";  // step | frame   (session::BatchingMode)
  int max_batch_size = 8;
  absl::Duration max_queue_delay = absl::Milliseconds(2);
  int max_queue_size = 64;       // per environment
  bool batch_invariant = false;  // frames independent of their batch, bitwise (slower)
  int max_sessions = 256;
  int max_sessions_per_environment = 256;
  int max_sessions_per_client = 16;
  absl::Duration idle_timeout = absl::Minutes(5);
  int max_frames_in_flight = 2;  // default and cap of OpenSession.max_frames_in_flight
  int max_steps = 50;            // cap on OpenSession.steps
  int min_size = 64;             // allowed frame width/height (multiples of 8)
  int max_size = 1024;
  int64_t max_message_bytes = 64 << 20;  // gRPC max receive message size
  std::string metrics_listen;            // e.g. "0.0.0.0:9464"; empty = no metrics endpoint
  std::string tls_cert;                  // PEM files; both or neither
  std::string tls_key;
  std::string tls_client_ca;     // optional: require client certificates signed by it
  std::string auth_tokens_file;  // optional bearer tokens (see auth.h); empty = no auth
  absl::Duration drain_timeout = absl::Seconds(30);  // graceful shutdown bound
  absl::Duration reaper_interval = absl::Seconds(10);
  bool reflection = true;           // gRPC server reflection
  std::string log_format = "json";  // json | text
};

// One option of the table, for callers that iterate it (tests, docs).
enum class OptionType { kString, kInt, kInt64, kDuration, kBool };
struct ServerConfigOption {
  std::string_view name;   // flag "--<name>" and config-file key "<name>"
  std::string_view group;  // heading in the --help text
  OptionType type;
  std::string_view help;  // one line
};

// Every option, in --help order. Thread-safety: thread-safe (immutable).
const std::vector<ServerConfigOption>& ServerConfigOptions();

// The option's value in `config` as its flag would spell it ("30s", "true",
// "8", a string as is). INVALID_ARGUMENT for an unknown name.
absl::StatusOr<std::string> FormatOptionValue(const ServerConfig& config, std::string_view name);

struct ParsedCommandLine {
  ServerConfig config;
  // --help / -h was given: the caller prints UsageText() and exits 0. The rest
  // of the command line is then not interpreted (config stays default).
  bool help = false;
  std::string config_file;  // --config, if given
};

// Parses argv[1..] (argv[0] is skipped), reading --config first, and returns a
// config that passed ValidateServerConfig. INVALID_ARGUMENT naming the flag:
// "unknown flag --foo", "--listen: missing value", "--max_batch_size:
// expected an integer >= 1, got 'x'", "unexpected argument 'x'", a repeated
// --config, and every ValidateServerConfig error; ParseConfigFile's errors
// for the file.
absl::StatusOr<ParsedCommandLine> ParseCommandLine(int argc, const char* const* argv);

// `base` with the options of the JSON object in `path` applied. Does not run
// ValidateServerConfig (flags may still change the result). Errors name the
// file and key: NOT_FOUND (no such file), INVALID_ARGUMENT (unreadable, not
// JSON, not an object, "unknown key 'foo'", a value of the wrong type or out
// of range).
absl::StatusOr<ServerConfig> ParseConfigFile(const std::string& path, ServerConfig base);

// INVALID_ARGUMENT naming the flag(s) unless every option is in range (the
// same per-option checks as parsing) and they agree: min_size <= max_size,
// tls_cert and tls_key both or neither, tls_client_ca only with them, listen
// and metrics_listen distinct.
absl::Status ValidateServerConfig(const ServerConfig& config);

// The --help text: usage line, then every option of the table with its
// default and one-line description, grouped.
std::string UsageText();

// kStepLevel for "step", kWholeFrame for "frame" (call after validation;
// anything else reads as "step").
session::BatchingMode ToBatchingMode(const ServerConfig& config);

}  // namespace fd::server

#endif  // FD_SERVER_SERVER_CONFIG_H_

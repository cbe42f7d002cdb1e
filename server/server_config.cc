#include "server/server_config.h"

#include <cerrno>
#include <cstring>
#include <fstream>
#include <limits>
#include <sstream>
#include <variant>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "nlohmann/json.hpp"
#include "session/frame_batcher.h"
#include "session/session_settings.h"

namespace fd::server {
namespace {

using Field =
    std::variant<std::string ServerConfig::*, int ServerConfig::*, int64_t ServerConfig::*,
                 absl::Duration ServerConfig::*, bool ServerConfig::*>;

// A string option's extra check; returns the problem without the flag name.
using StringCheck = absl::Status (*)(std::string_view value);

// One row of the table. Everything about an option lives here: its field,
// name, --help text and the range checks shared by flags, file and
// ValidateServerConfig.
struct Spec {
  std::string_view name;
  std::string_view group;
  std::string_view value_name;  // placeholder in --help, e.g. HOST:PORT
  std::string_view help;
  Field field;
  // Integers: the allowed range and step.
  int64_t min = 0;
  int64_t max = std::numeric_limits<int32_t>::max();
  int64_t multiple_of = 1;
  // Durations: whether zero is allowed (negative never is).
  bool allow_zero_duration = true;
  // Strings: the allowed values (empty = any) and an extra check.
  std::vector<std::string_view> choices = {};
  StringCheck check = nullptr;
};

std::string S(std::string_view text) { return std::string(text); }

// "[::]:50051", "localhost:0", "unix:/run/fd.sock": a host (possibly empty
// for gRPC's "any"), a colon and a port in [0, 65535].
absl::Status CheckAddress(std::string_view value, bool allow_unix) {
  if (allow_unix &&
      (absl::StartsWith(S(value), "unix:") || absl::StartsWith(S(value), "unix-abstract:"))) {
    return absl::OkStatus();
  }
  const size_t colon = value.rfind(':');
  uint32_t port = 0;
  if (colon == std::string_view::npos || colon == 0 ||
      !absl::SimpleAtoi(S(value.substr(colon + 1)), &port) || port > 65535 ||
      value.substr(colon + 1).find_first_not_of("0123456789") != std::string_view::npos) {
    return absl::InvalidArgumentError(
        absl::StrCat("expected HOST:PORT with a port in [0, 65535], got '", S(value), "'"));
  }
  return absl::OkStatus();
}

absl::Status CheckListen(std::string_view value) { return CheckAddress(value, true); }

absl::Status CheckMetricsListen(std::string_view value) {
  if (value.empty()) return absl::OkStatus();
  return CheckAddress(value, false);
}

// What LibTorch's device parser accepts for the devices we build for.
absl::Status CheckDevice(std::string_view value) {
  if (value == "cpu" || value == "cuda") return absl::OkStatus();
  uint32_t index = 0;
  if (absl::StartsWith(S(value), "cuda:") && value.size() > 5 &&
      value.substr(5).find_first_not_of("0123456789") == std::string_view::npos &&
      absl::SimpleAtoi(S(value.substr(5)), &index)) {
    return absl::OkStatus();
  }
  return absl::InvalidArgumentError(
      absl::StrCat("expected cpu, cuda or cuda:N, got '", S(value), "'"));
}

constexpr int64_t kMaxSide = static_cast<int64_t>(session::kMaxImageSide);

const std::vector<Spec>& Specs() {
  static const auto* specs = new std::vector<Spec>{
      // Network.
      {"listen",
       "Network",
       "HOST:PORT",
       "gRPC listen address; port 0 picks a free one (see --port_file)",
       &ServerConfig::listen,
       0,
       0,
       1,
       true,
       {},
       &CheckListen},
      {"port_file", "Network", "FILE",
       "once serving, write the bound gRPC port here (decimal and a newline)",
       &ServerConfig::port_file},
      {"max_message_bytes", "Network", "BYTES",
       "largest request message: a larger one ends its stream with RESOURCE_EXHAUSTED "
       "(the session stays resumable)",
       &ServerConfig::max_message_bytes, 1024, std::numeric_limits<int32_t>::max()},
      {"reflection", "Network", "BOOL", "serve gRPC server reflection", &ServerConfig::reflection},
      {"metrics_listen",
       "Network",
       "HOST:PORT",
       "Prometheus /metrics address, e.g. 0.0.0.0:9464; empty = no metrics endpoint",
       &ServerConfig::metrics_listen,
       0,
       0,
       1,
       true,
       {},
       &CheckMetricsListen},
      // Security.
      {"tls_cert", "Security", "FILE", "TLS certificate chain (PEM); needs --tls_key",
       &ServerConfig::tls_cert},
      {"tls_key", "Security", "FILE", "TLS private key (PEM); needs --tls_cert",
       &ServerConfig::tls_key},
      {"tls_client_ca", "Security", "FILE",
       "require client certificates signed by these CAs (PEM); needs TLS",
       &ServerConfig::tls_client_ca},
      {"auth_tokens_file", "Security", "FILE",
       "bearer tokens, lines of '<token> <client_identity>'; empty = no authentication",
       &ServerConfig::auth_tokens_file},
      // Model.
      {"model_repository", "Model", "DIR",
       "folder of environment checkpoint folders; empty = the embedded default environment",
       &ServerConfig::model_repository},
      {"device",
       "Model",
       "DEVICE",
       "torch device: cpu, cuda or cuda:N",
       &ServerConfig::device,
       0,
       0,
       1,
       true,
       {},
       &CheckDevice},
      {"dtype",
       "Model",
       "DTYPE",
       "model weights and activations: float32, float16 or bfloat16",
       &ServerConfig::dtype,
       0,
       0,
       1,
       true,
       {"float32", "float16", "bfloat16"}},
      {"threads", "Model", "N",
       "most torch intra-op threads of each batcher worker; 0 = the cores divided among the "
       "workers. Given alone, the workers become cores / N. Each environment runs at 1 or N "
       "threads, whichever its steps measured faster when it loaded, and runs the ControlNet "
       "beside "
       "the UNet on an idle core if that measured faster (log: intra_op_threads)",
       &ServerConfig::threads, 0, 1024},
      {"controlnet_beside_unet", "Model", "BOOL",
       "on a CPU with 2 or more cores, a frame's ControlNet may run beside its UNet's down path "
       "on a core no worker is using (a lone session's frames get faster; the result is the "
       "same), where its load-time measurement found that faster. false: never (say, when "
       "other processes share the cores)",
       &ServerConfig::controlnet_beside_unet},
      // Batching.
      {"batching",
       "Batching",
       "MODE",
       "step: frames join a running batch at every denoising step; frame: whole-frame batches",
       &ServerConfig::batching,
       0,
       0,
       1,
       true,
       {"step", "frame"}},
      {"max_batch_size", "Batching", "N", "most frames denoised together",
       &ServerConfig::max_batch_size, 1, 1024},
      {"max_queue_delay", "Batching", "DURATION",
       "how long a batch waits for more frames before it starts smaller",
       &ServerConfig::max_queue_delay},
      {"scheduler_workers", "Batching", "N",
       "worker threads per environment, each denoising its own batch of at most "
       "max_batch_size / N frames; 0 = auto: on a CPU one per core (at most max_batch_size), "
       "on a GPU 1 (small models use several cores better as 2 workers x 1 thread than as "
       "1 x 2)",
       &ServerConfig::scheduler_workers, 0, 64},
      {"batch_invariant", "Batching", "BOOL",
       "run convolutions and linear layers frame by frame inside a batch, so that a session's "
       "frames are bitwise the frames it gets alone, however busy the server (on a CPU 0-25% "
       "fewer frames/s, docs/BENCHMARKS.md; on a GPU it gives up most of batching's gain)",
       &ServerConfig::batch_invariant},
      {"max_queue_size", "Batching", "N",
       "most frames queued per environment; more are refused with RESOURCE_EXHAUSTED",
       &ServerConfig::max_queue_size, 1, 1 << 20},
      // Sessions.
      {"max_sessions", "Sessions", "N", "most live sessions in all", &ServerConfig::max_sessions, 1,
       1 << 20},
      {"max_sessions_per_environment", "Sessions", "N", "most live sessions per environment",
       &ServerConfig::max_sessions_per_environment, 1, 1 << 20},
      {"max_sessions_per_client", "Sessions", "N", "most live sessions per client identity",
       &ServerConfig::max_sessions_per_client, 1, 1 << 20},
      {"idle_timeout", "Sessions", "DURATION", "a session with no activity for this long expires",
       &ServerConfig::idle_timeout, 0, 0, 1, false},
      {"reaper_interval", "Sessions", "DURATION", "how often idle sessions are looked for",
       &ServerConfig::reaper_interval, 0, 0, 1, false},
      {"max_frames_in_flight", "Sessions", "N",
       "default and cap of OpenSession.max_frames_in_flight", &ServerConfig::max_frames_in_flight,
       1, 64},
      {"max_steps", "Sessions", "N", "cap on OpenSession.steps (denoising steps per frame)",
       &ServerConfig::max_steps, 1, 1000},
      {"min_size", "Sessions", "PIXELS", "smallest frame width/height (a multiple of 8)",
       &ServerConfig::min_size, 8, kMaxSide, 8},
      {"max_size", "Sessions", "PIXELS", "largest frame width/height (a multiple of 8)",
       &ServerConfig::max_size, 8, kMaxSide, 8},
      // Operations.
      {"drain_timeout", "Operations", "DURATION",
       "graceful shutdown: how long running sessions may finish before the server stops",
       &ServerConfig::drain_timeout},
      {"log_format",
       "Operations",
       "FORMAT",
       "log lines on stderr: json or text",
       &ServerConfig::log_format,
       0,
       0,
       1,
       true,
       {"json", "text"}},
  };
  return *specs;
}

const Spec* FindSpec(std::string_view name) {
  for (const Spec& spec : Specs()) {
    if (spec.name == name) return &spec;
  }
  return nullptr;
}

OptionType TypeOf(const Spec& spec) {
  return std::visit(
      [](auto member) {
        using T = std::remove_reference_t<decltype(std::declval<ServerConfig&>().*member)>;
        if constexpr (std::is_same_v<T, std::string>) return OptionType::kString;
        if constexpr (std::is_same_v<T, int>) return OptionType::kInt;
        if constexpr (std::is_same_v<T, int64_t>) return OptionType::kInt64;
        if constexpr (std::is_same_v<T, absl::Duration>) return OptionType::kDuration;
        if constexpr (std::is_same_v<T, bool>) return OptionType::kBool;
      },
      spec.field);
}

std::string IntegerExpectation(const Spec& spec) {
  // An int option up to INT_MAX has no upper bound worth printing.
  const bool unbounded =
      TypeOf(spec) == OptionType::kInt && spec.max == std::numeric_limits<int32_t>::max();
  std::string text = unbounded ? absl::StrCat("an integer >= ", spec.min)
                               : absl::StrCat("an integer in [", spec.min, ", ", spec.max, "]");
  if (spec.multiple_of > 1) absl::StrAppend(&text, ", a multiple of ", spec.multiple_of);
  return text;
}

std::string DurationExpectation(const Spec& spec) {
  return absl::StrCat("a duration ", spec.allow_zero_duration ? ">= 0" : "> 0",
                      " such as 250ms, 30s or 5m");
}

// Range checks of one typed value; the message does not name the option.
absl::Status CheckInteger(const Spec& spec, int64_t value, std::string_view text) {
  if (value < spec.min || value > spec.max || value % spec.multiple_of != 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("expected ", IntegerExpectation(spec), ", got '", S(text), "'"));
  }
  return absl::OkStatus();
}

absl::Status CheckDuration(const Spec& spec, absl::Duration value, std::string_view text) {
  if (value == absl::InfiniteDuration() || value < absl::ZeroDuration() ||
      (!spec.allow_zero_duration && value == absl::ZeroDuration())) {
    return absl::InvalidArgumentError(
        absl::StrCat("expected ", DurationExpectation(spec), ", got '", S(text), "'"));
  }
  return absl::OkStatus();
}

absl::Status CheckString(const Spec& spec, std::string_view value) {
  if (!spec.choices.empty()) {
    for (std::string_view choice : spec.choices) {
      if (value == choice) return absl::OkStatus();
    }
    std::vector<std::string> names(spec.choices.begin(), spec.choices.end());
    return absl::InvalidArgumentError(
        absl::StrCat("expected one of ", absl::StrJoin(names, ", "), ", got '", S(value), "'"));
  }
  if (spec.check != nullptr) return spec.check(value);
  return absl::OkStatus();
}

// Parses `text` into the option's field of `config`; the message does not
// name the option.
absl::Status SetFromText(const Spec& spec, std::string_view text, ServerConfig& config) {
  return std::visit(
      [&](auto member) -> absl::Status {
        auto& field = config.*member;
        using T = std::remove_reference_t<decltype(field)>;
        if constexpr (std::is_same_v<T, std::string>) {
          if (absl::Status status = CheckString(spec, text); !status.ok()) return status;
          field = std::string(text);
        } else if constexpr (std::is_same_v<T, int> || std::is_same_v<T, int64_t>) {
          T value{};
          if (!absl::SimpleAtoi(S(text), &value)) {
            return absl::InvalidArgumentError(
                absl::StrCat("expected ", IntegerExpectation(spec), ", got '", S(text), "'"));
          }
          if (absl::Status status = CheckInteger(spec, value, text); !status.ok()) return status;
          field = value;
        } else if constexpr (std::is_same_v<T, absl::Duration>) {
          absl::Duration value;
          if (!absl::ParseDuration(S(text), &value)) {
            return absl::InvalidArgumentError(
                absl::StrCat("expected ", DurationExpectation(spec), ", got '", S(text), "'"));
          }
          if (absl::Status status = CheckDuration(spec, value, text); !status.ok()) return status;
          field = value;
        } else if constexpr (std::is_same_v<T, bool>) {
          if (text == "true" || text == "1") {
            field = true;
          } else if (text == "false" || text == "0") {
            field = false;
          } else {
            return absl::InvalidArgumentError(
                absl::StrCat("expected true or false, got '", S(text), "'"));
          }
        }
        return absl::OkStatus();
      },
      spec.field);
}

// The checks of SetFromText on a value already in `config`.
absl::Status CheckField(const Spec& spec, const ServerConfig& config) {
  return std::visit(
      [&](auto member) -> absl::Status {
        const auto& field = config.*member;
        using T = std::remove_cv_t<std::remove_reference_t<decltype(field)>>;
        if constexpr (std::is_same_v<T, std::string>) {
          return CheckString(spec, field);
        } else if constexpr (std::is_same_v<T, int> || std::is_same_v<T, int64_t>) {
          return CheckInteger(spec, field, absl::StrCat(field));
        } else if constexpr (std::is_same_v<T, absl::Duration>) {
          return CheckDuration(spec, field, absl::FormatDuration(field));
        } else {
          return absl::OkStatus();
        }
      },
      spec.field);
}

std::string FormatField(const Spec& spec, const ServerConfig& config) {
  return std::visit(
      [&](auto member) -> std::string {
        const auto& field = config.*member;
        using T = std::remove_cv_t<std::remove_reference_t<decltype(field)>>;
        if constexpr (std::is_same_v<T, std::string>) {
          return field;
        } else if constexpr (std::is_same_v<T, absl::Duration>) {
          return absl::FormatDuration(field);
        } else if constexpr (std::is_same_v<T, bool>) {
          return field ? "true" : "false";
        } else {
          return absl::StrCat(field);
        }
      },
      spec.field);
}

absl::Status FlagError(std::string_view flag, const absl::Status& problem) {
  return absl::InvalidArgumentError(absl::StrCat("--", S(flag), ": ", problem.message()));
}

// The value of a config-file key as the text its flag would take, if the JSON
// type fits the option; else the problem.
absl::StatusOr<std::string> JsonValueText(const Spec& spec, const nlohmann::json& value) {
  switch (TypeOf(spec)) {
    case OptionType::kString:
      if (value.is_string()) return value.get<std::string>();
      return absl::InvalidArgumentError(absl::StrCat("expected a string, got ", value.dump()));
    case OptionType::kInt:
    case OptionType::kInt64:
      if (value.is_number_integer()) return value.dump();
      return absl::InvalidArgumentError(
          absl::StrCat("expected ", IntegerExpectation(spec), ", got ", value.dump()));
    case OptionType::kDuration:
      if (value.is_string()) return value.get<std::string>();
      return absl::InvalidArgumentError(
          absl::StrCat("expected ", DurationExpectation(spec), " as a string, got ", value.dump()));
    case OptionType::kBool:
      if (value.is_boolean()) return std::string(value.get<bool>() ? "true" : "false");
      return absl::InvalidArgumentError(absl::StrCat("expected true or false, got ", value.dump()));
  }
  return absl::InternalError("unreachable");
}

std::string NormalizeFlagName(std::string_view name) {
  std::string normalized(name);
  for (char& c : normalized) {
    if (c == '-') c = '_';
  }
  return normalized;
}

uint32_t PortOf(std::string_view address) {
  uint32_t port = 0;
  const size_t colon = address.rfind(':');
  if (colon == std::string_view::npos) return 0;
  if (!absl::SimpleAtoi(S(address.substr(colon + 1)), &port)) return 0;
  return port;
}

}  // namespace

const std::vector<ServerConfigOption>& ServerConfigOptions() {
  static const auto* options = [] {
    auto* list = new std::vector<ServerConfigOption>;
    for (const Spec& spec : Specs()) {
      list->push_back({spec.name, spec.group, TypeOf(spec), spec.help});
    }
    return list;
  }();
  return *options;
}

absl::StatusOr<std::string> FormatOptionValue(const ServerConfig& config, std::string_view name) {
  const Spec* spec = FindSpec(name);
  if (spec == nullptr) {
    return absl::InvalidArgumentError(absl::StrCat("unknown option '", S(name), "'"));
  }
  return FormatField(*spec, config);
}

absl::StatusOr<ServerConfig> ParseConfigFile(const std::string& path, ServerConfig base) {
  std::ifstream file(path, std::ios::binary);
  if (!file) {
    const int error = errno;
    if (error == ENOENT) return absl::NotFoundError(absl::StrCat(path, ": no such file"));
    return absl::InvalidArgumentError(absl::StrCat(path, ": cannot open: ", std::strerror(error)));
  }
  std::stringstream text;
  text << file.rdbuf();
  if (file.bad()) return absl::InvalidArgumentError(absl::StrCat(path, ": read failed"));

  nlohmann::json json;
  try {
    json = nlohmann::json::parse(text.str(), nullptr, /*allow_exceptions=*/true,
                                 /*ignore_comments=*/true);
  } catch (const nlohmann::json::parse_error& error) {
    return absl::InvalidArgumentError(
        absl::StrCat(path, ": not valid JSON (byte ", error.byte, "): ", error.what()));
  }
  if (!json.is_object()) {
    return absl::InvalidArgumentError(
        absl::StrCat(path, ": expected a JSON object of options, got ", json.type_name()));
  }
  for (const auto& [key, value] : json.items()) {
    const Spec* spec = FindSpec(key);
    if (spec == nullptr) {
      return absl::InvalidArgumentError(absl::StrCat(path, ": unknown key '", key, "'"));
    }
    absl::StatusOr<std::string> as_text = JsonValueText(*spec, value);
    absl::Status status = as_text.ok() ? SetFromText(*spec, *as_text, base) : as_text.status();
    if (!status.ok()) {
      return absl::InvalidArgumentError(
          absl::StrCat(path, ": key '", key, "': ", status.message()));
    }
  }
  return base;
}

absl::StatusOr<ParsedCommandLine> ParseCommandLine(int argc, const char* const* argv) {
  ParsedCommandLine parsed;
  for (int i = 1; i < argc; ++i) {
    const std::string_view arg = argv[i];
    if (arg == "--help" || arg == "-h") {
      parsed.help = true;
      return parsed;
    }
  }

  // First pass: split into (option, value) pairs and find --config, so that
  // flags apply on top of the file wherever they appear.
  struct FlagValue {
    const Spec* spec;
    std::string value;
  };
  std::vector<FlagValue> flags;
  bool have_config = false;
  for (int i = 1; i < argc; ++i) {
    const std::string_view arg = argv[i];
    if (!absl::StartsWith(S(arg), "--") || arg.size() == 2) {
      return absl::InvalidArgumentError(absl::StrCat("unexpected argument '", S(arg), "'"));
    }
    const size_t eq = arg.find('=');
    const std::string_view written = arg.substr(0, eq);
    const std::string name = NormalizeFlagName(written.substr(2));
    const Spec* spec = FindSpec(name);
    if (spec == nullptr && name != "config") {
      return absl::InvalidArgumentError(absl::StrCat("unknown flag ", S(written)));
    }
    std::string value;
    if (eq != std::string_view::npos) {
      value = std::string(arg.substr(eq + 1));
    } else if (spec != nullptr && TypeOf(*spec) == OptionType::kBool) {
      value = "true";
    } else if (i + 1 < argc && !absl::StartsWith(argv[i + 1], "--")) {
      value = argv[++i];
    } else {
      return absl::InvalidArgumentError(absl::StrCat("--", name, ": missing value"));
    }
    if (spec == nullptr) {  // --config
      if (have_config) return absl::InvalidArgumentError("--config: given more than once");
      if (value.empty()) return absl::InvalidArgumentError("--config: empty file name");
      have_config = true;
      parsed.config_file = value;
      continue;
    }
    flags.push_back({spec, std::move(value)});
  }

  if (have_config) {
    absl::StatusOr<ServerConfig> from_file = ParseConfigFile(parsed.config_file, parsed.config);
    if (!from_file.ok()) return from_file.status();
    parsed.config = *std::move(from_file);
  }
  for (const FlagValue& flag : flags) {
    if (absl::Status status = SetFromText(*flag.spec, flag.value, parsed.config); !status.ok()) {
      return FlagError(flag.spec->name, status);
    }
  }
  if (absl::Status status = ValidateServerConfig(parsed.config); !status.ok()) return status;
  return parsed;
}

absl::Status ValidateServerConfig(const ServerConfig& config) {
  for (const Spec& spec : Specs()) {
    if (absl::Status status = CheckField(spec, config); !status.ok()) {
      return FlagError(spec.name, status);
    }
  }
  if (config.min_size > config.max_size) {
    return absl::InvalidArgumentError(absl::StrCat(
        "--min_size (", config.min_size, ") must be <= --max_size (", config.max_size, ")"));
  }
  if (config.tls_cert.empty() != config.tls_key.empty()) {
    return absl::InvalidArgumentError(
        absl::StrCat("--tls_cert and --tls_key: give both or neither (only --",
                     config.tls_cert.empty() ? "tls_key" : "tls_cert", " is set)"));
  }
  if (!config.tls_client_ca.empty() && config.tls_cert.empty()) {
    return absl::InvalidArgumentError("--tls_client_ca: requires --tls_cert and --tls_key");
  }
  if (!config.metrics_listen.empty() && config.metrics_listen == config.listen &&
      PortOf(config.listen) != 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        "--metrics_listen: must differ from --listen, both are '", config.listen, "'"));
  }
  return absl::OkStatus();
}

std::string UsageText() {
  std::string text =
      "Usage: framediffuser-server [--config FILE] [--name=value | --name value]...\n"
      "\n"
      "Serves FrameDiffuser environments over gRPC (framediffuser.v1.FrameDiffuser).\n"
      "Options come from the defaults, then the JSON object in --config (keys are the\n"
      "option names), then the command line. Booleans: --name or --name=true|false.\n"
      "Durations: 250ms, 30s, 5m. Sizes: integers.\n"
      "\n"
      "General:\n"
      "  --config=FILE\n"
      "      JSON config file; flags on the command line override its keys\n"
      "  --help\n"
      "      print this text and exit\n";
  const ServerConfig defaults;
  std::string_view group;
  for (const Spec& spec : Specs()) {
    if (spec.group != group) {
      group = spec.group;
      absl::StrAppend(&text, "\n", S(group), ":\n");
    }
    const std::string value = FormatField(spec, defaults);
    absl::StrAppend(&text, "  --", S(spec.name), "=", S(spec.value_name), "\n      ", S(spec.help),
                    " [default: ", value.empty() ? "\"\"" : value, "]\n");
  }
  return text;
}

session::BatchingMode ToBatchingMode(const ServerConfig& config) {
  return config.batching == "frame" ? session::BatchingMode::kWholeFrame
                                    : session::BatchingMode::kStepLevel;
}

}  // namespace fd::server

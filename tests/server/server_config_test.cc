#include "server/server_config.h"

#include <unistd.h>

#include <cstdio>
#include <fstream>
#include <map>
#include <set>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "session/frame_batcher.h"

namespace fd::server {
namespace {

using ::testing::HasSubstr;
using ::testing::Not;

absl::StatusOr<ParsedCommandLine> Parse(const std::vector<std::string>& args) {
  std::vector<const char*> argv = {"framediffuser-server"};
  for (const std::string& arg : args) argv.push_back(arg.c_str());
  return ParseCommandLine(static_cast<int>(argv.size()), argv.data());
}

// A file under the test temp dir, unique per test and process, removed at
// the end of the test.
class TempFile {
 public:
  explicit TempFile(const std::string& contents) {
    const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
    path_ = absl::StrCat(::testing::TempDir(), "server_config_", info->name(), "_", getpid(), "_",
                         counter_++, ".json");
    std::ofstream(path_) << contents;
  }
  ~TempFile() { std::remove(path_.c_str()); }
  const std::string& path() const { return path_; }

 private:
  static inline int counter_ = 0;
  std::string path_;
};

// A non-default, mutually valid value for every option, as its flag spells
// it. ServerConfigOptionsAreAllCovered keeps it complete.
const std::map<std::string, std::string>& NonDefaultFlagValues() {
  static const auto* values = new std::map<std::string, std::string>{
      {"listen", "127.0.0.1:0"},
      {"port_file", "/tmp/fd_port"},
      {"model_repository", "/models"},
      {"device", "cuda:1"},
      {"dtype", "bfloat16"},
      {"threads", "3"},
      {"batching", "frame"},
      {"max_batch_size", "5"},
      {"max_queue_delay", "7ms"},
      {"max_queue_size", "9"},
      {"scheduler_workers", "6"},
      {"batch_invariant", "true"},
      {"controlnet_beside_unet", "false"},
      {"max_sessions", "11"},
      {"max_sessions_per_environment", "12"},
      {"max_sessions_per_client", "13"},
      {"idle_timeout", "2m"},
      {"max_frames_in_flight", "4"},
      {"max_steps", "20"},
      {"min_size", "128"},
      {"max_size", "2048"},
      {"max_message_bytes", "1048576"},
      {"metrics_listen", "127.0.0.1:9464"},
      {"tls_cert", "/c.pem"},
      {"tls_key", "/k.pem"},
      {"tls_client_ca", "/ca.pem"},
      {"auth_tokens_file", "/tokens"},
      {"drain_timeout", "45s"},
      {"reaper_interval", "1s"},
      {"reflection", "false"},
      {"log_format", "text"},
  };
  return *values;
}

// Field by field, so a table row wired to the wrong field is caught (the
// values differ pairwise).
void ExpectNonDefaults(const ServerConfig& c) {
  EXPECT_EQ(c.listen, "127.0.0.1:0");
  EXPECT_EQ(c.port_file, "/tmp/fd_port");
  EXPECT_EQ(c.model_repository, "/models");
  EXPECT_EQ(c.device, "cuda:1");
  EXPECT_EQ(c.dtype, "bfloat16");
  EXPECT_EQ(c.threads, 3);
  EXPECT_EQ(c.batching, "frame");
  EXPECT_EQ(c.max_batch_size, 5);
  EXPECT_EQ(c.max_queue_delay, absl::Milliseconds(7));
  EXPECT_EQ(c.max_queue_size, 9);
  EXPECT_EQ(c.scheduler_workers, 6);
  EXPECT_TRUE(c.batch_invariant);
  EXPECT_FALSE(c.controlnet_beside_unet);
  EXPECT_EQ(c.max_sessions, 11);
  EXPECT_EQ(c.max_sessions_per_environment, 12);
  EXPECT_EQ(c.max_sessions_per_client, 13);
  EXPECT_EQ(c.idle_timeout, absl::Minutes(2));
  EXPECT_EQ(c.max_frames_in_flight, 4);
  EXPECT_EQ(c.max_steps, 20);
  EXPECT_EQ(c.min_size, 128);
  EXPECT_EQ(c.max_size, 2048);
  EXPECT_EQ(c.max_message_bytes, 1048576);
  EXPECT_EQ(c.metrics_listen, "127.0.0.1:9464");
  EXPECT_EQ(c.tls_cert, "/c.pem");
  EXPECT_EQ(c.tls_key, "/k.pem");
  EXPECT_EQ(c.tls_client_ca, "/ca.pem");
  EXPECT_EQ(c.auth_tokens_file, "/tokens");
  EXPECT_EQ(c.drain_timeout, absl::Seconds(45));
  EXPECT_EQ(c.reaper_interval, absl::Seconds(1));
  EXPECT_FALSE(c.reflection);
  EXPECT_EQ(c.log_format, "text");
}

// The same values as a JSON config file (typed: numbers, booleans, strings).
std::string NonDefaultJson() {
  std::string json = "{\n  // comments are allowed\n";
  bool first = true;
  for (const ServerConfigOption& option : ServerConfigOptions()) {
    const std::string& text = NonDefaultFlagValues().at(std::string(option.name));
    const bool bare = option.type == OptionType::kInt || option.type == OptionType::kInt64 ||
                      option.type == OptionType::kBool;
    absl::StrAppend(&json, first ? "" : ",\n", "  \"", std::string(option.name),
                    "\": ", bare ? text : absl::StrCat("\"", text, "\""));
    first = false;
  }
  return json + "\n}\n";
}

TEST(ServerConfigTest, OptionTableIsWellFormed) {
  std::set<std::string> names;
  for (const ServerConfigOption& option : ServerConfigOptions()) {
    EXPECT_TRUE(names.insert(std::string(option.name)).second) << option.name;
    EXPECT_FALSE(option.group.empty()) << option.name;
    EXPECT_FALSE(option.help.empty()) << option.name;
    EXPECT_NE(option.name, "config");
    EXPECT_NE(option.name, "help");
  }
}

TEST(ServerConfigTest, ServerConfigOptionsAreAllCovered) {
  std::set<std::string> table;
  for (const ServerConfigOption& option : ServerConfigOptions()) {
    table.insert(std::string(option.name));
  }
  std::set<std::string> tested;
  for (const auto& [name, unused] : NonDefaultFlagValues()) tested.insert(name);
  EXPECT_EQ(table, tested);
}

TEST(ServerConfigTest, NoArgumentsGiveDefaults) {
  absl::StatusOr<ParsedCommandLine> parsed = Parse({});
  ASSERT_TRUE(parsed.ok()) << parsed.status();
  EXPECT_FALSE(parsed->help);
  EXPECT_TRUE(parsed->config_file.empty());
  const ServerConfig defaults;
  for (const ServerConfigOption& option : ServerConfigOptions()) {
    EXPECT_EQ(*FormatOptionValue(parsed->config, option.name),
              *FormatOptionValue(defaults, option.name))
        << option.name;
  }
  EXPECT_TRUE(ValidateServerConfig(defaults).ok());
}

TEST(ServerConfigTest, EveryOptionSettableByFlagWithEquals) {
  std::vector<std::string> args;
  for (const auto& [name, value] : NonDefaultFlagValues()) {
    args.push_back(absl::StrCat("--", name, "=", value));
  }
  absl::StatusOr<ParsedCommandLine> parsed = Parse(args);
  ASSERT_TRUE(parsed.ok()) << parsed.status();
  ExpectNonDefaults(parsed->config);
  for (const auto& [name, value] : NonDefaultFlagValues()) {
    EXPECT_EQ(*FormatOptionValue(parsed->config, name), value) << name;
  }
}

TEST(ServerConfigTest, EveryNonBooleanOptionSettableByFlagWithSpace) {
  std::vector<std::string> args;
  for (const ServerConfigOption& option : ServerConfigOptions()) {
    const std::string& value = NonDefaultFlagValues().at(std::string(option.name));
    if (option.type == OptionType::kBool) {  // a bare boolean flag takes no value
      args.push_back(absl::StrCat("--", std::string(option.name), "=", value));
      continue;
    }
    args.push_back(absl::StrCat("--", std::string(option.name)));
    args.push_back(value);
  }
  absl::StatusOr<ParsedCommandLine> parsed = Parse(args);
  ASSERT_TRUE(parsed.ok()) << parsed.status();
  ExpectNonDefaults(parsed->config);
}

TEST(ServerConfigTest, EveryOptionSettableByConfigFile) {
  TempFile file(NonDefaultJson());
  absl::StatusOr<ServerConfig> config = ParseConfigFile(file.path(), ServerConfig());
  ASSERT_TRUE(config.ok()) << config.status();
  ExpectNonDefaults(*config);

  absl::StatusOr<ParsedCommandLine> parsed = Parse({"--config", file.path()});
  ASSERT_TRUE(parsed.ok()) << parsed.status();
  EXPECT_EQ(parsed->config_file, file.path());
  ExpectNonDefaults(parsed->config);
}

TEST(ServerConfigTest, ConfigFileKeepsBaseForKeysItLacks) {
  TempFile file(R"({"max_steps": 7})");
  ServerConfig base;
  base.max_batch_size = 3;
  absl::StatusOr<ServerConfig> config = ParseConfigFile(file.path(), base);
  ASSERT_TRUE(config.ok()) << config.status();
  EXPECT_EQ(config->max_steps, 7);
  EXPECT_EQ(config->max_batch_size, 3);
}

TEST(ServerConfigTest, FlagsOverrideConfigFileWhereverTheyAppear) {
  TempFile file(R"({"max_batch_size": 4, "listen": "127.0.0.1:7000", "reflection": false})");
  for (const auto& args : std::vector<std::vector<std::string>>{
           {"--max_batch_size=5", "--config", file.path(), "--reflection"},
           {"--config=" + file.path(), "--max_batch_size", "5", "--reflection=true"}}) {
    absl::StatusOr<ParsedCommandLine> parsed = Parse(args);
    ASSERT_TRUE(parsed.ok()) << parsed.status();
    EXPECT_EQ(parsed->config.max_batch_size, 5);
    EXPECT_EQ(parsed->config.listen, "127.0.0.1:7000");
    EXPECT_TRUE(parsed->config.reflection);
  }
}

TEST(ServerConfigTest, BooleanForms) {
  EXPECT_TRUE(Parse({"--reflection"})->config.reflection);
  EXPECT_TRUE(Parse({"--reflection=true"})->config.reflection);
  EXPECT_TRUE(Parse({"--reflection=1"})->config.reflection);
  EXPECT_FALSE(Parse({"--reflection=false"})->config.reflection);
  EXPECT_FALSE(Parse({"--reflection=0"})->config.reflection);
  // A bare boolean does not take the next argument.
  EXPECT_THAT(Parse({"--reflection", "false"}).status().message(),
              HasSubstr("unexpected argument 'false'"));
}

TEST(ServerConfigTest, DashesReadAsUnderscores) {
  absl::StatusOr<ParsedCommandLine> parsed = Parse({"--max-batch-size=3", "--idle-timeout", "1h"});
  ASSERT_TRUE(parsed.ok()) << parsed.status();
  EXPECT_EQ(parsed->config.max_batch_size, 3);
  EXPECT_EQ(parsed->config.idle_timeout, absl::Hours(1));
}

TEST(ServerConfigTest, LastFlagWins) {
  EXPECT_EQ(Parse({"--max_steps=3", "--max_steps=4"})->config.max_steps, 4);
}

TEST(ServerConfigTest, EmptyStringValues) {
  absl::StatusOr<ParsedCommandLine> parsed = Parse({"--metrics_listen=", "--port_file="});
  ASSERT_TRUE(parsed.ok()) << parsed.status();
  EXPECT_EQ(parsed->config.metrics_listen, "");
}

TEST(ServerConfigTest, Help) {
  EXPECT_TRUE(Parse({"--help"})->help);
  EXPECT_TRUE(Parse({"-h"})->help);
  // --help wins over anything else on the line.
  EXPECT_TRUE(Parse({"--bogus", "--help"})->help);
}

void ExpectInvalid(const std::vector<std::string>& args, const std::string& message) {
  absl::StatusOr<ParsedCommandLine> parsed = Parse(args);
  ASSERT_FALSE(parsed.ok()) << absl::StrCat(args.empty() ? "" : args[0]);
  EXPECT_EQ(parsed.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(parsed.status().message(), HasSubstr(message));
}

TEST(ServerConfigTest, FlagErrorsNameTheFlag) {
  ExpectInvalid({"--max_batch_size=x"},
                "--max_batch_size: expected an integer in [1, 1024], got 'x'");
  ExpectInvalid({"--max_batch_size", "0"},
                "--max_batch_size: expected an integer in [1, 1024], got '0'");
  ExpectInvalid({"--threads=-1"}, "--threads: expected an integer in [0, 1024], got '-1'");
  ExpectInvalid({"--max_message_bytes=12"},
                "--max_message_bytes: expected an integer in [1024, 2147483647], got '12'");
  ExpectInvalid({"--max_message_bytes=99999999999"}, "--max_message_bytes:");
  ExpectInvalid({"--min_size=100"},
                "--min_size: expected an integer in [8, 4096], a multiple of 8, got '100'");
  ExpectInvalid({"--idle_timeout=soon"}, "--idle_timeout: expected a duration > 0");
  ExpectInvalid({"--idle_timeout=0s"}, "--idle_timeout: expected a duration > 0");
  ExpectInvalid({"--idle_timeout=inf"}, "--idle_timeout:");
  ExpectInvalid({"--max_queue_delay=-1ms"}, "--max_queue_delay: expected a duration >= 0");
  ExpectInvalid({"--max_queue_delay=5"}, "--max_queue_delay:");  // no unit
  ExpectInvalid({"--reflection=maybe"}, "--reflection: expected true or false, got 'maybe'");
  ExpectInvalid({"--dtype=float64"},
                "--dtype: expected one of float32, float16, bfloat16, got 'float64'");
  ExpectInvalid({"--batching=batch"}, "--batching: expected one of step, frame, got 'batch'");
  ExpectInvalid({"--log_format=xml"}, "--log_format: expected one of json, text, got 'xml'");
  ExpectInvalid({"--device=gpu"}, "--device: expected cpu, cuda or cuda:N, got 'gpu'");
  ExpectInvalid({"--device=cuda:x"}, "--device:");
  ExpectInvalid({"--listen=localhost"}, "--listen: expected HOST:PORT");
  ExpectInvalid({"--listen=localhost:70000"}, "--listen: expected HOST:PORT");
  ExpectInvalid({"--listen="}, "--listen:");
  ExpectInvalid({"--metrics_listen=unix:/x"}, "--metrics_listen:");
}

TEST(ServerConfigTest, UnixListenAddressIsAccepted) {
  EXPECT_EQ(Parse({"--listen=unix:/tmp/fd.sock"})->config.listen, "unix:/tmp/fd.sock");
}

TEST(ServerConfigTest, CommandLineShapeErrors) {
  ExpectInvalid({"--foo"}, "unknown flag --foo");
  ExpectInvalid({"--foo=1"}, "unknown flag --foo");
  ExpectInvalid({"--listen"}, "--listen: missing value");
  ExpectInvalid({"--listen", "--max_steps=3"}, "--listen: missing value");
  ExpectInvalid({"serve"}, "unexpected argument 'serve'");
  ExpectInvalid({"-v"}, "unexpected argument '-v'");
  ExpectInvalid({"--"}, "unexpected argument '--'");
  ExpectInvalid({"--config"}, "--config: missing value");
  ExpectInvalid({"--config=a.json", "--config=b.json"}, "--config: given more than once");
}

TEST(ServerConfigTest, CommandLineIsValidatedAsAWhole) {
  ExpectInvalid({"--min_size=512", "--max_size=256"},
                "--min_size (512) must be <= --max_size (256)");
  ExpectInvalid({"--tls_cert=/c.pem"}, "--tls_cert and --tls_key: give both or neither");
}

TEST(ServerConfigTest, ConfigFileErrorsNameFileAndKey) {
  {
    TempFile file(R"({"max_batch_size": 4, "bogus": 1})");
    absl::StatusOr<ServerConfig> config = ParseConfigFile(file.path(), ServerConfig());
    EXPECT_EQ(config.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(config.status().message(), HasSubstr(file.path() + ": unknown key 'bogus'"));
  }
  {
    TempFile file(R"({"max_batch_size": "4"})");
    EXPECT_THAT(ParseConfigFile(file.path(), ServerConfig()).status().message(),
                HasSubstr(file.path() +
                          ": key 'max_batch_size': expected an integer in [1, 1024], got \"4\""));
  }
  {
    TempFile file(R"({"max_batch_size": 0})");
    EXPECT_THAT(ParseConfigFile(file.path(), ServerConfig()).status().message(),
                HasSubstr(file.path() +
                          ": key 'max_batch_size': expected an integer in [1, 1024], got '0'"));
  }
  {
    TempFile file(R"({"max_batch_size": 2.5})");
    EXPECT_THAT(ParseConfigFile(file.path(), ServerConfig()).status().message(),
                HasSubstr("key 'max_batch_size': expected an integer"));
  }
  {
    TempFile file(R"({"idle_timeout": 30})");
    EXPECT_THAT(ParseConfigFile(file.path(), ServerConfig()).status().message(),
                HasSubstr("key 'idle_timeout': expected a duration > 0 such as 250ms, 30s or 5m as "
                          "a string, got 30"));
  }
  {
    TempFile file(R"({"reflection": "yes"})");
    EXPECT_THAT(ParseConfigFile(file.path(), ServerConfig()).status().message(),
                HasSubstr("key 'reflection': expected true or false, got \"yes\""));
  }
  {
    TempFile file(R"({"listen": 50051})");
    EXPECT_THAT(ParseConfigFile(file.path(), ServerConfig()).status().message(),
                HasSubstr("key 'listen': expected a string, got 50051"));
  }
  {
    TempFile file(R"({"dtype": "int8"})");
    EXPECT_THAT(ParseConfigFile(file.path(), ServerConfig()).status().message(),
                HasSubstr("key 'dtype': expected one of float32, float16, bfloat16, got 'int8'"));
  }
  {
    TempFile file("{\"listen\": ");
    absl::StatusOr<ServerConfig> config = ParseConfigFile(file.path(), ServerConfig());
    EXPECT_EQ(config.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(config.status().message(), HasSubstr(file.path() + ": not valid JSON"));
  }
  {
    TempFile file("[1, 2]");
    EXPECT_THAT(ParseConfigFile(file.path(), ServerConfig()).status().message(),
                HasSubstr(file.path() + ": expected a JSON object of options, got array"));
  }
  {
    TempFile file(R"({"config": "other.json"})");
    EXPECT_THAT(ParseConfigFile(file.path(), ServerConfig()).status().message(),
                HasSubstr("unknown key 'config'"));
  }
}

TEST(ServerConfigTest, MissingConfigFileIsNotFound) {
  const std::string path = absl::StrCat(::testing::TempDir(), "no_such_config_", getpid(), ".json");
  absl::StatusOr<ServerConfig> config = ParseConfigFile(path, ServerConfig());
  EXPECT_EQ(config.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(config.status().message(), HasSubstr(path));

  absl::StatusOr<ParsedCommandLine> parsed = Parse({"--config", path});
  EXPECT_EQ(parsed.status().code(), absl::StatusCode::kNotFound);
}

TEST(ServerConfigTest, ConfigFileErrorsComeThroughTheCommandLine) {
  TempFile file(R"({"max_steps": -2})");
  absl::StatusOr<ParsedCommandLine> parsed = Parse({"--config", file.path()});
  EXPECT_EQ(parsed.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(parsed.status().message(), HasSubstr(file.path() + ": key 'max_steps'"));
}

TEST(ServerConfigTest, FileValuesAreValidatedAfterFlags) {
  // The file alone is inconsistent; the flag fixes it.
  TempFile file(R"({"min_size": 2048})");
  absl::StatusOr<ParsedCommandLine> parsed = Parse({"--config", file.path(), "--max_size=4096"});
  ASSERT_TRUE(parsed.ok()) << parsed.status();
  EXPECT_EQ(parsed->config.min_size, 2048);
}

void ExpectValidationError(const ServerConfig& config, const std::string& message) {
  absl::Status status = ValidateServerConfig(config);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(status.message(), HasSubstr(message));
}

TEST(ServerConfigTest, ValidationErrors) {
  ServerConfig c;
  c.max_steps = 0;
  ExpectValidationError(c, "--max_steps: expected an integer in [1, 1000], got '0'");
  c = ServerConfig();
  c.max_size = 1004;
  ExpectValidationError(
      c, "--max_size: expected an integer in [8, 4096], a multiple of 8, got '1004'");
  c = ServerConfig();
  c.min_size = 2048;
  ExpectValidationError(c, "--min_size (2048) must be <= --max_size (1024)");
  c = ServerConfig();
  c.tls_cert = "/c.pem";
  ExpectValidationError(c,
                        "--tls_cert and --tls_key: give both or neither (only --tls_cert is set)");
  c = ServerConfig();
  c.tls_key = "/k.pem";
  ExpectValidationError(c, "(only --tls_key is set)");
  c = ServerConfig();
  c.tls_client_ca = "/ca.pem";
  ExpectValidationError(c, "--tls_client_ca: requires --tls_cert and --tls_key");
  c = ServerConfig();
  c.reaper_interval = absl::ZeroDuration();
  ExpectValidationError(c, "--reaper_interval: expected a duration > 0");
  c = ServerConfig();
  c.drain_timeout = -absl::Seconds(1);
  ExpectValidationError(c, "--drain_timeout: expected a duration >= 0");
  c = ServerConfig();
  c.dtype = "fp16";
  ExpectValidationError(c, "--dtype: expected one of");
  c = ServerConfig();
  c.device = "";
  ExpectValidationError(c, "--device:");
  c = ServerConfig();
  c.metrics_listen = c.listen;
  ExpectValidationError(c, "--metrics_listen: must differ from --listen");

  c = ServerConfig();
  c.tls_cert = "/c.pem";
  c.tls_key = "/k.pem";
  c.tls_client_ca = "/ca.pem";
  c.drain_timeout = absl::ZeroDuration();  // stop at once
  c.threads = 0;
  c.listen = "[::]:0";
  c.metrics_listen = "[::]:0";  // both pick a free port
  EXPECT_TRUE(ValidateServerConfig(c).ok()) << ValidateServerConfig(c);
}

TEST(ServerConfigTest, UsageTextMentionsEveryOptionWithItsDefault) {
  const std::string usage = UsageText();
  const ServerConfig defaults;
  EXPECT_THAT(usage, HasSubstr("--config=FILE"));
  EXPECT_THAT(usage, HasSubstr("--help"));
  for (const ServerConfigOption& option : ServerConfigOptions()) {
    const std::string flag = absl::StrCat("--", std::string(option.name), "=");
    const size_t at = usage.find(flag);
    ASSERT_NE(at, std::string::npos) << option.name;
    const std::string value = *FormatOptionValue(defaults, option.name);
    const std::string entry = usage.substr(at, usage.find("\n  --", at) - at);
    EXPECT_THAT(entry, HasSubstr(std::string(option.help))) << option.name;
    EXPECT_THAT(entry, HasSubstr(absl::StrCat("[default: ", value.empty() ? "\"\"" : value, "]")))
        << option.name;
    EXPECT_THAT(usage, HasSubstr(absl::StrCat("\n", std::string(option.group), ":\n")));
  }
  EXPECT_THAT(usage, HasSubstr("[default: 0.0.0.0:50051]"));
  EXPECT_THAT(usage, HasSubstr("[default: 2ms]"));
  EXPECT_THAT(usage, Not(HasSubstr("\t")));
}

TEST(ServerConfigTest, FormatOptionValue) {
  ServerConfig c;
  EXPECT_EQ(*FormatOptionValue(c, "idle_timeout"), "5m");
  EXPECT_EQ(*FormatOptionValue(c, "reflection"), "true");
  EXPECT_EQ(*FormatOptionValue(c, "max_message_bytes"), "67108864");
  EXPECT_EQ(FormatOptionValue(c, "nope").status().code(), absl::StatusCode::kInvalidArgument);
}

TEST(ServerConfigTest, ToBatchingMode) {
  ServerConfig c;
  EXPECT_EQ(ToBatchingMode(c), session::BatchingMode::kStepLevel);
  c.batching = "frame";
  EXPECT_EQ(ToBatchingMode(c), session::BatchingMode::kWholeFrame);
}

}  // namespace
}  // namespace fd::server

#include "server/log.h"

#include <cstdint>
#include <limits>
#include <map>
#include <string>
#include <thread>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "nlohmann/json.hpp"

namespace fd::server {
namespace {

using ::testing::HasSubstr;
using ::testing::MatchesRegex;
using ::testing::Not;
using ::testing::SizeIs;

const absl::Time kTime = absl::FromUnixMillis(1714564800123);  // 2024-05-01T12:00:00.123Z

TEST(LogTest, JsonLineHasFixedKeysFirstThenFieldsInOrder) {
  const std::string line = FormatLogLine(LogFormat::kJson, kTime, LogLevel::kInfo, "session_open",
                                         {{"session_id", "0123abcd"},
                                          {"environment", std::string("street")},
                                          {"width", 512},
                                          {"frames", int64_t{-3}},
                                          {"seed", std::numeric_limits<uint64_t>::max()},
                                          {"ratio", 0.5},
                                          {"resumed", false}});
  EXPECT_EQ(line, R"({"ts":"2024-05-01T12:00:00.123Z","level":"info","event":"session_open",)"
                  R"("session_id":"0123abcd","environment":"street","width":512,"frames":-3,)"
                  R"("seed":18446744073709551615,"ratio":0.5,"resumed":false})");
}

TEST(LogTest, JsonEscapesStrings) {
  const std::string value = "say \"hi\"\\ \n\t\x01 caf\xc3\xa9";
  const std::string line =
      FormatLogLine(LogFormat::kJson, kTime, LogLevel::kError, "bad\"event", {{"detail", value}});
  EXPECT_THAT(line, Not(HasSubstr("\n")));
  EXPECT_THAT(line, HasSubstr(R"("detail":"say \"hi\"\\ \n\t\u0001 café")"));
  const nlohmann::json parsed = nlohmann::json::parse(line);
  EXPECT_EQ(parsed["detail"], value);
  EXPECT_EQ(parsed["event"], "bad\"event");
  EXPECT_EQ(parsed["level"], "error");
}

TEST(LogTest, JsonReplacesInvalidUtf8InsteadOfThrowing) {
  std::string line;
  EXPECT_NO_THROW(line = FormatLogLine(LogFormat::kJson, kTime, LogLevel::kInfo, "e",
                                       {{"bytes", std::string_view("a\xff\xfe"
                                                                   "b")}}));
  const nlohmann::json parsed = nlohmann::json::parse(line);
  EXPECT_EQ(parsed["bytes"],
            "a\xef\xbf\xbd\xef\xbf\xbd"
            "b");
}

TEST(LogTest, ReservedKeysDoNotOverwriteTheFixedOnes) {
  const std::string line = FormatLogLine(LogFormat::kJson, kTime, LogLevel::kInfo, "real",
                                         {{"event", "fake"}, {"ts", 1}, {"level", "x"}});
  const nlohmann::json parsed = nlohmann::json::parse(line);
  EXPECT_EQ(parsed["event"], "real");
  EXPECT_EQ(parsed["level"], "info");
  EXPECT_EQ(parsed["ts"], "2024-05-01T12:00:00.123Z");
  EXPECT_EQ(parsed["field_event"], "fake");
  EXPECT_EQ(parsed["field_ts"], 1);
  EXPECT_EQ(parsed["field_level"], "x");
}

TEST(LogTest, TextLine) {
  const std::string line = FormatLogLine(
      LogFormat::kText, kTime, LogLevel::kWarning, "env_load",
      {{"name", "street"}, {"steps", 10}, {"seconds", 1.25}, {"ok", true}, {"seed", uint64_t{7}}});
  EXPECT_EQ(line,
            "2024-05-01T12:00:00.123Z warning env_load name=street steps=10 seconds=1.25 ok=true "
            "seed=7");
}

TEST(LogTest, TextQuotesValuesThatNeedIt) {
  const std::string line = FormatLogLine(LogFormat::kText, kTime, LogLevel::kInfo, "e",
                                         {{"path", "/a b"},
                                          {"empty", ""},
                                          {"quote", "say \"hi\""},
                                          {"eq", "a=b"},
                                          {"nl", "x\ny\r\tz"},
                                          {"bs", "c:\\d"},
                                          {"ctl", "\x01"},
                                          {"utf8", "caf\xc3\xa9"}});
  EXPECT_EQ(line,
            "2024-05-01T12:00:00.123Z info e path=\"/a b\" empty=\"\" quote=\"say \\\"hi\\\"\" "
            "eq=\"a=b\" nl=\"x\\ny\\r\\tz\" bs=\"c:\\\\d\" ctl=\"\\x01\" utf8=caf\xc3\xa9");
}

TEST(LogTest, TextSanitisesKeysAndEvent) {
  const std::string line = FormatLogLine(LogFormat::kText, kTime, LogLevel::kInfo, "an event",
                                         {{"a b=c", 1}, {"", 2}, {"ts", 3}});
  EXPECT_EQ(line, "2024-05-01T12:00:00.123Z info an_event a_b_c=1 _=2 field_ts=3");
}

TEST(LogTest, ParseLogFormat) {
  EXPECT_EQ(*ParseLogFormat("json"), LogFormat::kJson);
  EXPECT_EQ(*ParseLogFormat("text"), LogFormat::kText);
  absl::StatusOr<LogFormat> bad = ParseLogFormat("xml");
  EXPECT_EQ(bad.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(bad.status().message(), HasSubstr("log_format: expected json or text, got 'xml'"));
}

TEST(LogTest, LevelNames) {
  EXPECT_EQ(LogLevelName(LogLevel::kInfo), "info");
  EXPECT_EQ(LogLevelName(LogLevel::kWarning), "warning");
  EXPECT_EQ(LogLevelName(LogLevel::kError), "error");
}

TEST(LogTest, ProcessLoggerWritesToTheSinkInTheChosenFormat) {
  const LogFormat before = GetLogFormat();
  {
    ScopedLogCapture capture(LogFormat::kJson);
    LogEvent("server_start", {{"listen", "127.0.0.1:1234"}});
    LogWarning("slow_frame", {{"ms", 12.5}});
    LogError("session_error", {{"code", "INTERNAL"}});
    Log(LogLevel::kInfo, "server_stop");
    const std::vector<std::string> lines = capture.lines();
    ASSERT_THAT(lines, SizeIs(4));
    const nlohmann::json start = nlohmann::json::parse(lines[0]);
    EXPECT_EQ(start["event"], "server_start");
    EXPECT_EQ(start["level"], "info");
    EXPECT_EQ(start["listen"], "127.0.0.1:1234");
    EXPECT_THAT(start["ts"].get<std::string>(),
                MatchesRegex("[0-9]{4}-[0-9]{2}-[0-9]{2}T[0-9]{2}:[0-9]{2}:[0-9]{2}\\.[0-9]{3}Z"));
    EXPECT_EQ(nlohmann::json::parse(lines[1])["level"], "warning");
    EXPECT_EQ(nlohmann::json::parse(lines[2])["level"], "error");
    EXPECT_EQ(nlohmann::json::parse(lines[3]).size(), 3u);
  }
  {
    ScopedLogCapture capture(LogFormat::kText);
    EXPECT_EQ(GetLogFormat(), LogFormat::kText);
    LogEvent("server_stop", {{"reason", "SIGTERM"}});
    ASSERT_THAT(capture.lines(), SizeIs(1));
    EXPECT_THAT(capture.lines()[0], MatchesRegex(".*Z info server_stop reason=SIGTERM"));
  }
  EXPECT_EQ(GetLogFormat(), before);
}

TEST(LogTest, SetLogSinkReturnsThePreviousSink) {
  std::vector<std::string> first;
  std::vector<std::string> second;
  LogSink original = SetLogSink([&](std::string_view line) { first.emplace_back(line); });
  LogEvent("a");
  LogSink previous = SetLogSink([&](std::string_view line) { second.emplace_back(line); });
  LogEvent("b");
  previous("direct");
  SetLogSink(std::move(original));
  EXPECT_THAT(first, SizeIs(2));
  EXPECT_THAT(second, SizeIs(1));
}

// Lines from 4 threads stay whole: the sink appends each line in pieces to
// one shared buffer with no lock of its own (yielding in between), so only
// the logger's serialisation keeps the lines apart.
TEST(LogTest, ConcurrentLinesNeverInterleave) {
  constexpr int kThreads = 4;
  constexpr int kLinesPerThread = 200;
  std::string buffer;  // guarded by the logger's lock
  ScopedLogCapture restore;
  SetLogSink([&buffer](std::string_view line) {
    const size_t half = line.size() / 2;
    buffer.append(line.substr(0, half));
    std::this_thread::yield();
    buffer.append(line.substr(half));
    buffer.push_back('\n');
  });
  const std::string payload(500, 'x');
  std::vector<std::thread> threads;
  for (int t = 0; t < kThreads; ++t) {
    threads.emplace_back([t, &payload] {
      for (int i = 0; i < kLinesPerThread; ++i) {
        LogEvent("tick", {{"thread", t}, {"i", i}, {"payload", payload}});
      }
    });
  }
  for (std::thread& thread : threads) thread.join();
  SetLogSink(nullptr);

  std::vector<std::string> lines = absl::StrSplit(buffer, '\n', absl::SkipEmpty());
  ASSERT_THAT(lines, SizeIs(kThreads * kLinesPerThread));
  std::map<int, int> next_index;  // per thread, lines arrive in order
  for (const std::string& line : lines) {
    const nlohmann::json parsed = nlohmann::json::parse(line);
    const int thread = parsed["thread"];
    EXPECT_EQ(parsed["i"], next_index[thread]++);
    EXPECT_EQ(parsed["payload"], payload);
  }
  for (int t = 0; t < kThreads; ++t) EXPECT_EQ(next_index[t], kLinesPerThread);
}

}  // namespace
}  // namespace fd::server

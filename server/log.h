// Structured event log of framediffuser-server: one line per event (session
// open/close/error, environment load, server start/stop), written whole to
// stderr or to an injected sink.
//
//   LogEvent("session_open", {{"session_id", id}, {"environment", env}, {"width", 512}});
//
// JSON (default), one object per line, keys in this order:
//   {"ts":"2024-05-01T12:00:00.123Z","level":"info","event":"session_open","session_id":"..."}
// text:
//   2024-05-01T12:00:00.123Z info session_open session_id=ab12 environment="down town"
// Text values are quoted (with \" \\ \n \r \t and \xNN escapes) when empty or
// when they hold a space, '"', '=', '\\' or a control character.
//
// SECRETS: callers must never pass resume tokens, bearer tokens, TLS keys or
// anything else that grants access. Session ids are public (load balancers see
// them) and may be logged; resume secrets may not.
#ifndef FD_SERVER_LOG_H_
#define FD_SERVER_LOG_H_

#include <cstdint>
#include <functional>
#include <initializer_list>
#include <memory>
#include <string>
#include <string_view>
#include <type_traits>
#include <variant>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"

namespace fd::server {

enum class LogLevel { kInfo, kWarning, kError };
enum class LogFormat { kJson, kText };

// "info", "warning", "error".
std::string_view LogLevelName(LogLevel level);
// "json" or "text"; INVALID_ARGUMENT naming the value otherwise.
absl::StatusOr<LogFormat> ParseLogFormat(std::string_view name);

// One key=value of an event. Borrows the key and string values: build fields
// inline in the LogEvent call (they live until the end of the statement).
// Integers keep their sign (uint64 seeds above 2^63 stay exact).
struct LogField {
  using Value = std::variant<std::string_view, int64_t, uint64_t, double, bool>;

  LogField(std::string_view key, std::string_view value) : key(key), value(value) {}
  LogField(std::string_view key, const char* value) : key(key), value(std::string_view(value)) {}
  LogField(std::string_view key, const std::string& value)
      : key(key), value(std::string_view(value)) {}
  LogField(std::string_view key, bool value) : key(key), value(value) {}
  LogField(std::string_view key, double value) : key(key), value(value) {}
  LogField(std::string_view key, float value) : key(key), value(static_cast<double>(value)) {}
  template <typename T,
            std::enable_if_t<std::is_integral_v<T> && !std::is_same_v<T, bool>, int> = 0>
  LogField(std::string_view key, T value) : key(key), value(ToInteger(value)) {}

  std::string_view key;
  Value value;

 private:
  template <typename T>
  static Value ToInteger(T value) {
    if constexpr (std::is_signed_v<T>) {
      return static_cast<int64_t>(value);
    } else {
      return static_cast<uint64_t>(value);
    }
  }
};

// Receives each whole line, without the trailing newline. Called with the
// logger's lock held (so lines never interleave): it must not log.
using LogSink = std::function<void(std::string_view line)>;

// The line for one event (pure; what LogEvent writes). Field keys "ts",
// "level" and "event" are reserved: such a field is written as "field_<key>".
// Invalid UTF-8 in JSON output is replaced by U+FFFD.
std::string FormatLogLine(LogFormat format, absl::Time time, LogLevel level, std::string_view event,
                          std::initializer_list<LogField> fields);

// The process-wide logger. Thread-safety: every function here is thread-safe;
// a line is formatted outside the lock and written whole under it.
void LogEvent(std::string_view event, std::initializer_list<LogField> fields = {});  // info
void LogWarning(std::string_view event, std::initializer_list<LogField> fields = {});
void LogError(std::string_view event, std::initializer_list<LogField> fields = {});
void Log(LogLevel level, std::string_view event, std::initializer_list<LogField> fields = {});

void SetLogFormat(LogFormat format);  // default kJson
LogFormat GetLogFormat();
// Replaces the sink and returns the previous one; an empty function means the
// default: stderr, flushed per line.
LogSink SetLogSink(LogSink sink);

// For tests: captures every line logged while it lives (in the given format)
// and restores the previous sink and format when destroyed. Not nestable
// across threads that create and destroy captures concurrently.
// Thread-safety: lines() may be called while other threads log.
class ScopedLogCapture {
 public:
  explicit ScopedLogCapture(LogFormat format = LogFormat::kJson);
  ~ScopedLogCapture();
  ScopedLogCapture(const ScopedLogCapture&) = delete;
  ScopedLogCapture& operator=(const ScopedLogCapture&) = delete;

  std::vector<std::string> lines() const;

 private:
  struct Captured {
    mutable absl::Mutex mu;
    std::vector<std::string> lines ABSL_GUARDED_BY(mu);
  };
  std::shared_ptr<Captured> captured_;
  LogSink previous_sink_;
  LogFormat previous_format_;
};

}  // namespace fd::server

#endif  // FD_SERVER_LOG_H_

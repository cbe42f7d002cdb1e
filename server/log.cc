#include "server/log.h"

#include <atomic>
#include <cstdio>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "nlohmann/json.hpp"

namespace fd::server {
namespace {

struct Logger {
  absl::Mutex mu;
  LogSink sink ABSL_GUARDED_BY(mu);
  std::atomic<LogFormat> format{LogFormat::kJson};
};

Logger& GetLogger() {
  static Logger* logger = new Logger;  // never destroyed: threads may log during exit
  return *logger;
}

std::string Timestamp(absl::Time time) {
  return absl::FormatTime("%Y-%m-%dT%H:%M:%E3SZ", time, absl::UTCTimeZone());
}

std::string FieldKey(std::string_view key) {
  if (key == "ts" || key == "level" || key == "event")
    return absl::StrCat("field_", std::string(key));
  return std::string(key);
}

// Keys and event names in text lines: [A-Za-z0-9_.-], anything else '_', so a
// key can never break the key=value structure.
std::string TextName(std::string_view name) {
  if (name.empty()) return "_";
  std::string out(name);
  for (char& c : out) {
    const bool ok = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') ||
                    c == '_' || c == '.' || c == '-';
    if (!ok) c = '_';
  }
  return out;
}

bool IsControl(char c) {
  const auto u = static_cast<unsigned char>(c);
  return u < 0x20 || u == 0x7f;
}

std::string TextValue(std::string_view value) {
  bool quote = value.empty();
  for (char c : value) {
    if (c == ' ' || c == '"' || c == '=' || c == '\\' || IsControl(c)) quote = true;
  }
  if (!quote) return std::string(value);
  std::string out = "\"";
  for (char c : value) {
    switch (c) {
      case '"':
        out += "\\\"";
        break;
      case '\\':
        out += "\\\\";
        break;
      case '\n':
        out += "\\n";
        break;
      case '\r':
        out += "\\r";
        break;
      case '\t':
        out += "\\t";
        break;
      default:
        if (IsControl(c)) {
          absl::StrAppendFormat(&out, "\\x%02x", static_cast<unsigned char>(c));
        } else {
          out += c;
        }
    }
  }
  out += '"';
  return out;
}

std::string TextOf(const LogField::Value& value) {
  return std::visit(
      [](const auto& v) -> std::string {
        using T = std::decay_t<decltype(v)>;
        if constexpr (std::is_same_v<T, std::string_view>) {
          return TextValue(v);
        } else if constexpr (std::is_same_v<T, bool>) {
          return v ? "true" : "false";
        } else {
          return absl::StrCat(v);
        }
      },
      value);
}

nlohmann::ordered_json JsonOf(const LogField::Value& value) {
  return std::visit(
      [](const auto& v) -> nlohmann::ordered_json {
        using T = std::decay_t<decltype(v)>;
        if constexpr (std::is_same_v<T, std::string_view>) {
          return std::string(v);
        } else {
          return v;
        }
      },
      value);
}

void Write(std::string line) {
  Logger& logger = GetLogger();
  absl::MutexLock lock(&logger.mu);
  if (logger.sink) {
    logger.sink(line);
    return;
  }
  line += '\n';
  std::fwrite(line.data(), 1, line.size(), stderr);
  std::fflush(stderr);
}

}  // namespace

std::string_view LogLevelName(LogLevel level) {
  switch (level) {
    case LogLevel::kInfo:
      return "info";
    case LogLevel::kWarning:
      return "warning";
    case LogLevel::kError:
      return "error";
  }
  return "info";
}

absl::StatusOr<LogFormat> ParseLogFormat(std::string_view name) {
  if (name == "json") return LogFormat::kJson;
  if (name == "text") return LogFormat::kText;
  return absl::InvalidArgumentError(
      absl::StrCat("log_format: expected json or text, got '", std::string(name), "'"));
}

std::string FormatLogLine(LogFormat format, absl::Time time, LogLevel level, std::string_view event,
                          std::initializer_list<LogField> fields) {
  if (format == LogFormat::kText) {
    std::string line =
        absl::StrCat(Timestamp(time), " ", std::string(LogLevelName(level)), " ", TextName(event));
    for (const LogField& field : fields) {
      absl::StrAppend(&line, " ", TextName(FieldKey(field.key)), "=", TextOf(field.value));
    }
    return line;
  }
  nlohmann::ordered_json json;
  json["ts"] = Timestamp(time);
  json["level"] = std::string(LogLevelName(level));
  json["event"] = std::string(event);
  for (const LogField& field : fields) json[FieldKey(field.key)] = JsonOf(field.value);
  // Replace, not throw, on invalid UTF-8: a log line must never take the
  // server down.
  return json.dump(-1, ' ', /*ensure_ascii=*/false, nlohmann::json::error_handler_t::replace);
}

void Log(LogLevel level, std::string_view event, std::initializer_list<LogField> fields) {
  Write(FormatLogLine(GetLogFormat(), absl::Now(), level, event, fields));
}

void LogEvent(std::string_view event, std::initializer_list<LogField> fields) {
  Log(LogLevel::kInfo, event, fields);
}

void LogWarning(std::string_view event, std::initializer_list<LogField> fields) {
  Log(LogLevel::kWarning, event, fields);
}

void LogError(std::string_view event, std::initializer_list<LogField> fields) {
  Log(LogLevel::kError, event, fields);
}

void SetLogFormat(LogFormat format) { GetLogger().format.store(format); }

LogFormat GetLogFormat() { return GetLogger().format.load(); }

LogSink SetLogSink(LogSink sink) {
  Logger& logger = GetLogger();
  absl::MutexLock lock(&logger.mu);
  std::swap(logger.sink, sink);
  return sink;
}

ScopedLogCapture::ScopedLogCapture(LogFormat format)
    : captured_(std::make_shared<Captured>()), previous_format_(GetLogFormat()) {
  SetLogFormat(format);
  previous_sink_ = SetLogSink([captured = captured_](std::string_view line) {
    absl::MutexLock lock(&captured->mu);
    captured->lines.emplace_back(line);
  });
}

ScopedLogCapture::~ScopedLogCapture() {
  SetLogSink(std::move(previous_sink_));
  SetLogFormat(previous_format_);
}

std::vector<std::string> ScopedLogCapture::lines() const {
  absl::MutexLock lock(&captured_->mu);
  return captured_->lines;
}

}  // namespace fd::server

// Property checks inside fuzz targets: a failed check is a crash that
// libFuzzer (or the standalone driver) reports with its input.
#ifndef FD_TESTS_FUZZ_FUZZ_CHECK_H_
#define FD_TESTS_FUZZ_FUZZ_CHECK_H_

#include <algorithm>
#include <cstdio>
#include <cstdlib>

#include "absl/status/status.h"
#include "absl/strings/string_view.h"

// Aborts with `what` when `condition` is false.
#define FD_FUZZ_CHECK(condition, what)                                                            \
  do {                                                                                            \
    if (!(condition)) {                                                                           \
      std::fprintf(stderr, "%s:%d: fuzz check failed: %s (%s)\n", __FILE__, __LINE__, #condition, \
                   what);                                                                         \
      std::abort();                                                                               \
    }                                                                                             \
  } while (false)

namespace fd::fuzz {

// Every error built from untrusted input names its field and stays short
// (issue 19: no message echoes unbounded input). 1 KiB leaves room for a
// path and a 128-byte quote.
inline constexpr size_t kMaxErrorMessageBytes = 1024;

// Checks an error for the contract of the parsers under test: the expected
// code, a message that starts with `prefix` and is bounded.
inline void CheckError(const absl::Status& status, absl::StatusCode code,
                       absl::string_view prefix) {
  FD_FUZZ_CHECK(!status.ok(), "expected an error");
  if (status.code() != code) {
    std::fprintf(stderr, "unexpected status: %s\n", status.ToString().c_str());
  }
  FD_FUZZ_CHECK(status.code() == code, "status code");
  const absl::string_view message = status.message();
  if (message.substr(0, prefix.size()) != prefix) {
    std::fprintf(stderr, "message without the prefix '%.*s': %.*s\n", int(prefix.size()),
                 prefix.data(), int(std::min<size_t>(message.size(), 2048)), message.data());
  }
  FD_FUZZ_CHECK(message.substr(0, prefix.size()) == prefix, "message names the field");
  FD_FUZZ_CHECK(message.size() <= kMaxErrorMessageBytes, "bounded message");
}

}  // namespace fd::fuzz

#endif  // FD_TESTS_FUZZ_FUZZ_CHECK_H_

#include "session/random_token.h"

#include <fcntl.h>
#include <sys/random.h>
#include <unistd.h>

#include <cerrno>
#include <cstdint>
#include <cstring>

#include "absl/strings/str_cat.h"

namespace fd::session {
namespace {

// Fills `out` with `size` bytes from getrandom(2) (blocking only until the
// kernel's pool is initialised, once per boot). False if unavailable.
bool FillFromGetrandom(uint8_t* out, size_t size) {
  size_t filled = 0;
  while (filled < size) {
    const ssize_t n = getrandom(out + filled, size - filled, 0);
    if (n < 0) {
      if (errno == EINTR) continue;
      return false;  // e.g. ENOSYS on an old kernel or a seccomp filter
    }
    filled += static_cast<size_t>(n);
  }
  return true;
}

bool FillFromUrandom(uint8_t* out, size_t size) {
  const int fd = open("/dev/urandom", O_RDONLY | O_CLOEXEC);
  if (fd < 0) return false;
  size_t filled = 0;
  while (filled < size) {
    const ssize_t n = read(fd, out + filled, size - filled);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) {
      close(fd);
      return false;
    }
    filled += static_cast<size_t>(n);
  }
  close(fd);
  return true;
}

}  // namespace

absl::StatusOr<std::string> NewRandomToken() {
  uint8_t bytes[kTokenHexChars / 2];
  if (!FillFromGetrandom(bytes, sizeof(bytes)) && !FillFromUrandom(bytes, sizeof(bytes))) {
    return absl::InternalError(
        absl::StrCat("no OS randomness for a session id: ", std::strerror(errno)));
  }
  static constexpr char kHex[] = "0123456789abcdef";
  std::string token(kTokenHexChars, '0');
  for (size_t i = 0; i < sizeof(bytes); ++i) {
    token[2 * i] = kHex[bytes[i] >> 4];
    token[2 * i + 1] = kHex[bytes[i] & 0xf];
  }
  return token;
}

bool IsWellFormedToken(std::string_view token) {
  if (token.size() != kTokenHexChars) return false;
  for (char c : token) {
    if (!((c >= '0' && c <= '9') || (c >= 'a' && c <= 'f'))) return false;
  }
  return true;
}

bool ConstantTimeEquals(std::string_view a, std::string_view b) {
  // Lengths are not secret (every token has kTokenHexChars characters).
  if (a.size() != b.size()) return false;
  // volatile keeps the compiler from ending the loop at the first difference.
  volatile uint8_t diff = 0;
  for (size_t i = 0; i < a.size(); ++i) {
    diff = diff | (static_cast<uint8_t>(a[i]) ^ static_cast<uint8_t>(b[i]));
  }
  return diff == 0;
}

}  // namespace fd::session

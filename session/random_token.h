// Session ids and resume secrets: 128 bits from the operating system's CSPRNG
// (getrandom(2), falling back to /dev/urandom), written as 32 lowercase hex
// characters.
#ifndef FD_SESSION_RANDOM_TOKEN_H_
#define FD_SESSION_RANDOM_TOKEN_H_

#include <string>
#include <string_view>

#include "absl/status/statusor.h"

namespace fd::session {

// Characters of a token: 128 bits as lowercase hex.
inline constexpr size_t kTokenHexChars = 32;

// A fresh 128-bit random token. INTERNAL if the OS has no randomness to give
// (getrandom and /dev/urandom both failed). Thread-safety: thread-safe.
absl::StatusOr<std::string> NewRandomToken();

// True for exactly kTokenHexChars characters of [0-9a-f].
bool IsWellFormedToken(std::string_view token);

// Compares secrets in time that depends only on their lengths, not on where
// they first differ (so a resume attempt cannot learn a secret byte by byte).
bool ConstantTimeEquals(std::string_view a, std::string_view b);

}  // namespace fd::session

#endif  // FD_SESSION_RANDOM_TOKEN_H_

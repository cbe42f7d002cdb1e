// Bearer-token authentication of RPCs ("authorization: Bearer <token>").
//
// Token file (--auth_tokens_file), one token per line:
//   # comment
//   <token> <client_identity>
// Blank lines and lines whose first non-blank character is '#' are ignored.
// Tokens are at least kMinTokenChars visible ASCII characters and unique; a
// client identity (one word) may own several tokens, e.g. while rotating.
// The identity is what per-client session limits and session ownership use.
//
// Without a token file the server runs without authentication: a
// default-constructed TokenAuthenticator is disabled and every call gets the
// identity "" (all clients share it).
//
// Tokens are secrets: no message, log line or error here contains one, and
// a presented token is compared with every known token in time that does not
// depend on where they differ.
#ifndef FD_SERVER_AUTH_H_
#define FD_SERVER_AUTH_H_

#include <grpcpp/server_context.h>
#include <grpcpp/support/string_ref.h>

#include <cstddef>
#include <map>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"

namespace fd::server {

inline constexpr size_t kMinTokenChars = 16;

// Value type; cheap to move. Thread-safety: const methods are thread-safe.
class TokenAuthenticator {
 public:
  // Disabled: Authenticate() accepts every call as identity "".
  TokenAuthenticator() = default;

  // Reads a token file. NOT_FOUND if it does not exist; INVALID_ARGUMENT
  // naming "path:line" for a malformed line, a short or duplicate token
  // (never the token itself), or "path: no tokens" for a file without any.
  static absl::StatusOr<TokenAuthenticator> LoadTokenFile(const std::string& path);
  // The same from text; `source` names it in errors (used for "path").
  static absl::StatusOr<TokenAuthenticator> FromText(std::string_view text,
                                                     std::string_view source);

  // Whether tokens were loaded (false: no authentication).
  bool enabled() const { return !entries_.empty(); }
  size_t token_count() const { return entries_.size(); }

  // The client identity of an "authorization" metadata value; an empty value
  // means the metadata is absent. Disabled: "" for anything. UNAUTHENTICATED:
  //   "missing authorization metadata"
  //   "authorization: expected 'Bearer <token>'" (the scheme is
  //       case-insensitive, as RFC 7235 says)
  //   "unknown bearer token"
  absl::StatusOr<std::string> Authenticate(std::string_view authorization_header_value) const;

 private:
  struct Entry {
    std::string token;
    std::string identity;
  };
  std::vector<Entry> entries_;
};

// Authenticates a call from its client metadata ("authorization" key; gRPC
// lowercases metadata keys). UNAUTHENTICATED as Authenticate(), and
// "authorization: expected one value, got N" for repeated metadata.
absl::StatusOr<std::string> AuthenticateMetadata(
    const TokenAuthenticator& authenticator,
    const std::multimap<grpc::string_ref, grpc::string_ref>& client_metadata);

// The same for a server call (grpc::CallbackServerContext or ServerContext).
absl::StatusOr<std::string> AuthenticateCall(const TokenAuthenticator& authenticator,
                                             const grpc::ServerContextBase& context);

}  // namespace fd::server

#endif  // FD_SERVER_AUTH_H_

#include "server/auth.h"

#include <cerrno>
#include <cstring>
#include <fstream>
#include <sstream>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "session/random_token.h"

namespace fd::server {
namespace {

bool IsBlank(char c) { return c == ' ' || c == '\t'; }

std::string_view TrimBlanks(std::string_view text) {
  while (!text.empty() && (IsBlank(text.front()) || text.front() == '\r')) text.remove_prefix(1);
  while (!text.empty() && (IsBlank(text.back()) || text.back() == '\r')) text.remove_suffix(1);
  return text;
}

// Characters a token may hold: visible ASCII, what an HTTP/2 header value
// carries without escaping (and what RFC 6750's b64token is a subset of).
bool IsTokenChar(char c) { return c > 0x20 && c < 0x7f; }

// Splits a line on blanks.
std::vector<std::string_view> Words(std::string_view line) {
  std::vector<std::string_view> words;
  size_t i = 0;
  while (i < line.size()) {
    while (i < line.size() && IsBlank(line[i])) ++i;
    const size_t start = i;
    while (i < line.size() && !IsBlank(line[i])) ++i;
    if (i > start) words.push_back(line.substr(start, i - start));
  }
  return words;
}

}  // namespace

absl::StatusOr<TokenAuthenticator> TokenAuthenticator::LoadTokenFile(const std::string& path) {
  std::ifstream file(path, std::ios::binary);
  if (!file) {
    const int error = errno;
    if (error == ENOENT) return absl::NotFoundError(absl::StrCat(path, ": no such file"));
    return absl::InvalidArgumentError(absl::StrCat(path, ": cannot open: ", std::strerror(error)));
  }
  std::stringstream text;
  text << file.rdbuf();
  if (file.bad()) return absl::InvalidArgumentError(absl::StrCat(path, ": read failed"));
  return FromText(text.str(), path);
}

absl::StatusOr<TokenAuthenticator> TokenAuthenticator::FromText(std::string_view text,
                                                                std::string_view source) {
  const std::string name(source);
  TokenAuthenticator authenticator;
  std::vector<int> first_line;  // per entry, the line it came from
  int line_number = 0;
  size_t start = 0;
  while (start <= text.size()) {
    size_t end = text.find('\n', start);
    if (end == std::string_view::npos) end = text.size();
    const std::string_view line = TrimBlanks(text.substr(start, end - start));
    start = end + 1;
    ++line_number;
    if (line.empty() || line.front() == '#') continue;

    const std::string where = absl::StrCat(name, ":", line_number, ": ");
    const std::vector<std::string_view> words = Words(line);
    if (words.size() != 2) {
      return absl::InvalidArgumentError(
          absl::StrCat(where, "expected '<token> <client_identity>', got ", words.size(),
                       words.size() == 1 ? " word" : " words"));
    }
    const std::string_view token = words[0];
    const std::string_view identity = words[1];
    if (token.size() < kMinTokenChars) {
      return absl::InvalidArgumentError(absl::StrCat(
          where, "token has ", token.size(), " characters, expected at least ", kMinTokenChars));
    }
    for (char c : line) {
      if (!IsBlank(c) && !IsTokenChar(c)) {
        return absl::InvalidArgumentError(absl::StrCat(
            where, "expected visible ASCII characters only (a control or non-ASCII byte)"));
      }
    }
    for (size_t i = 0; i < authenticator.entries_.size(); ++i) {
      if (authenticator.entries_[i].token == token) {
        return absl::InvalidArgumentError(
            absl::StrCat(where, "duplicate token (first on line ", first_line[i], ")"));
      }
    }
    authenticator.entries_.push_back({std::string(token), std::string(identity)});
    first_line.push_back(line_number);
  }
  if (authenticator.entries_.empty()) {
    return absl::InvalidArgumentError(absl::StrCat(name, ": no tokens"));
  }
  return authenticator;
}

absl::StatusOr<std::string> TokenAuthenticator::Authenticate(
    std::string_view authorization_header_value) const {
  if (!enabled()) return std::string();
  const std::string_view value = TrimBlanks(authorization_header_value);
  if (value.empty()) return absl::UnauthenticatedError("missing authorization metadata");

  constexpr std::string_view kScheme = "bearer";
  std::string_view token;
  if (value.size() > kScheme.size() && IsBlank(value[kScheme.size()]) &&
      absl::EqualsIgnoreCase(absl::string_view(value.data(), kScheme.size()),
                             absl::string_view(kScheme.data(), kScheme.size()))) {
    token = TrimBlanks(value.substr(kScheme.size()));
  }
  bool well_formed = !token.empty();
  for (char c : token) well_formed = well_formed && IsTokenChar(c);
  if (!well_formed) {
    return absl::UnauthenticatedError("authorization: expected 'Bearer <token>'");
  }

  // Compare with every token, without stopping at a match, so the time taken
  // does not say which token (or how much of one) matched.
  const Entry* match = nullptr;
  for (const Entry& entry : entries_) {
    const bool equal = session::ConstantTimeEquals(token, entry.token);
    if (equal) match = &entry;
  }
  if (match == nullptr) return absl::UnauthenticatedError("unknown bearer token");
  return match->identity;
}

absl::StatusOr<std::string> AuthenticateMetadata(
    const TokenAuthenticator& authenticator,
    const std::multimap<grpc::string_ref, grpc::string_ref>& client_metadata) {
  if (!authenticator.enabled()) return std::string();
  const auto [begin, end] = client_metadata.equal_range("authorization");
  const auto count = std::distance(begin, end);
  if (count == 0) return absl::UnauthenticatedError("missing authorization metadata");
  if (count > 1) {
    return absl::UnauthenticatedError(
        absl::StrCat("authorization: expected one value, got ", count));
  }
  return authenticator.Authenticate(std::string_view(begin->second.data(), begin->second.size()));
}

absl::StatusOr<std::string> AuthenticateCall(const TokenAuthenticator& authenticator,
                                             const grpc::ServerContextBase& context) {
  return AuthenticateMetadata(authenticator, context.client_metadata());
}

}  // namespace fd::server

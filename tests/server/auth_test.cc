#include "server/auth.h"

#include <grpcpp/server_context.h>
#include <grpcpp/test/server_context_test_spouse.h>
#include <unistd.h>

#include <cstdio>
#include <fstream>
#include <map>
#include <string>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace fd::server {
namespace {

using ::testing::HasSubstr;
using ::testing::Not;

constexpr char kAliceToken[] = "alice-token-0123456789";
constexpr char kAliceToken2[] = "alice-rotated-abcdefghij";
constexpr char kBobToken[] = "bob_token_ABCDEFGHIJKLMNOP";

std::string TokenFileText() {
  return absl::StrCat("# bearer tokens\n", "\n", kAliceToken, " alice\n", "  # indented comment\n",
                      kBobToken, "\tbob\r\n",  // CRLF and a tab
                      "   ", kAliceToken2, "   alice   \n");
}

// A file under the test temp dir, unique per test and process.
class TempFile {
 public:
  explicit TempFile(const std::string& contents) {
    const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
    path_ = absl::StrCat(::testing::TempDir(), "auth_", info->name(), "_", getpid(), ".tokens");
    std::ofstream(path_, std::ios::binary) << contents;
  }
  ~TempFile() { std::remove(path_.c_str()); }
  const std::string& path() const { return path_; }

 private:
  std::string path_;
};

TokenAuthenticator Loaded() {
  absl::StatusOr<TokenAuthenticator> auth = TokenAuthenticator::FromText(TokenFileText(), "t");
  EXPECT_TRUE(auth.ok()) << auth.status();
  return *std::move(auth);
}

void ExpectUnauthenticated(const absl::StatusOr<std::string>& result, const std::string& message) {
  ASSERT_FALSE(result.ok()) << *result;
  EXPECT_EQ(result.status().code(), absl::StatusCode::kUnauthenticated);
  EXPECT_EQ(result.status().message(), message);
}

TEST(AuthTest, LoadsTokenFile) {
  TempFile file(TokenFileText());
  absl::StatusOr<TokenAuthenticator> auth = TokenAuthenticator::LoadTokenFile(file.path());
  ASSERT_TRUE(auth.ok()) << auth.status();
  EXPECT_TRUE(auth->enabled());
  EXPECT_EQ(auth->token_count(), 3u);
  EXPECT_EQ(*auth->Authenticate(absl::StrCat("Bearer ", kAliceToken)), "alice");
  EXPECT_EQ(*auth->Authenticate(absl::StrCat("Bearer ", kAliceToken2)), "alice");
  EXPECT_EQ(*auth->Authenticate(absl::StrCat("Bearer ", kBobToken)), "bob");
}

TEST(AuthTest, SchemeIsCaseInsensitiveAndBlanksAreTolerated) {
  const TokenAuthenticator auth = Loaded();
  EXPECT_EQ(*auth.Authenticate(absl::StrCat("bearer ", kBobToken)), "bob");
  EXPECT_EQ(*auth.Authenticate(absl::StrCat("BEARER ", kBobToken)), "bob");
  EXPECT_EQ(*auth.Authenticate(absl::StrCat("Bearer   ", kBobToken, "  ")), "bob");
  EXPECT_EQ(*auth.Authenticate(absl::StrCat("Bearer\t", kBobToken)), "bob");
}

TEST(AuthTest, MissingHeader) {
  const TokenAuthenticator auth = Loaded();
  ExpectUnauthenticated(auth.Authenticate(""), "missing authorization metadata");
  ExpectUnauthenticated(auth.Authenticate("   "), "missing authorization metadata");
}

TEST(AuthTest, MalformedHeader) {
  const TokenAuthenticator auth = Loaded();
  for (const std::string& value :
       {std::string("Basic dXNlcjpwYXNz"), std::string("Bearer"), std::string("Bearer    "),
        absl::StrCat("Bearer", kAliceToken), std::string(kAliceToken),
        absl::StrCat("Bearer ", kAliceToken, " extra"), absl::StrCat("Token ", kAliceToken),
        absl::StrCat("Bearer ", kAliceToken, "\x01")}) {
    SCOPED_TRACE(value);
    const absl::StatusOr<std::string> result = auth.Authenticate(value);
    ExpectUnauthenticated(result, "authorization: expected 'Bearer <token>'");
  }
}

TEST(AuthTest, UnknownTokenIsRejectedWithoutEchoingIt) {
  const TokenAuthenticator auth = Loaded();
  const std::string alice(kAliceToken);
  for (const std::string& token :
       {std::string("not-a-known-token-at-all"), alice.substr(0, alice.size() - 1), alice + "9",
        std::string("ALICE-TOKEN-0123456789"), std::string("x")}) {
    SCOPED_TRACE(token);
    const absl::StatusOr<std::string> result = auth.Authenticate("Bearer " + token);
    ExpectUnauthenticated(result, "unknown bearer token");
    EXPECT_THAT(std::string(result.status().message()), Not(HasSubstr(token)));
  }
}

TEST(AuthTest, DisabledAuthenticatorAcceptsEveryoneAsTheEmptyIdentity) {
  const TokenAuthenticator auth;
  EXPECT_FALSE(auth.enabled());
  EXPECT_EQ(*auth.Authenticate(""), "");
  EXPECT_EQ(*auth.Authenticate("Bearer whatever"), "");
  EXPECT_EQ(*auth.Authenticate("garbage"), "");
}

void ExpectFileError(const std::string& text, const std::string& message) {
  absl::StatusOr<TokenAuthenticator> auth = TokenAuthenticator::FromText(text, "tokens.txt");
  ASSERT_FALSE(auth.ok());
  EXPECT_EQ(auth.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(auth.status().message()), HasSubstr(message));
}

TEST(AuthTest, TokenFileErrorsNameFileAndLine) {
  ExpectFileError("# only comments\n\n", "tokens.txt: no tokens");
  ExpectFileError("", "tokens.txt: no tokens");
  ExpectFileError(absl::StrCat("# c\n", kAliceToken, "\n"),
                  "tokens.txt:2: expected '<token> <client_identity>', got 1 word");
  ExpectFileError(absl::StrCat(kAliceToken, " alice smith\n"),
                  "tokens.txt:1: expected '<token> <client_identity>', got 3 words");
  ExpectFileError("\n\nshort-token alice\n",
                  "tokens.txt:3: token has 11 characters, expected at least 16");
  ExpectFileError(absl::StrCat(kAliceToken, " alice\n", kBobToken, " bob\n", kAliceToken, " eve\n"),
                  "tokens.txt:3: duplicate token (first on line 1)");
  ExpectFileError(absl::StrCat(kAliceToken, " al\x01ice\n"),
                  "tokens.txt:1: expected visible ASCII characters only");
  ExpectFileError(absl::StrCat(kAliceToken, " caf\xc3\xa9\n"),
                  "tokens.txt:1: expected visible ASCII characters only");
}

TEST(AuthTest, TokenFileErrorsNeverContainTheToken) {
  const std::string secret = "s3cr3t";
  absl::StatusOr<TokenAuthenticator> auth =
      TokenAuthenticator::FromText(secret + " alice\n", "tokens.txt");
  ASSERT_FALSE(auth.ok());
  EXPECT_THAT(std::string(auth.status().message()), Not(HasSubstr(secret)));

  auth = TokenAuthenticator::FromText(absl::StrCat(kAliceToken, " a\n", kAliceToken, " b\n"), "f");
  ASSERT_FALSE(auth.ok());
  EXPECT_THAT(std::string(auth.status().message()), Not(HasSubstr(kAliceToken)));
}

TEST(AuthTest, MissingTokenFileIsNotFound) {
  const std::string path = absl::StrCat(::testing::TempDir(), "no_such_tokens_", getpid());
  absl::StatusOr<TokenAuthenticator> auth = TokenAuthenticator::LoadTokenFile(path);
  EXPECT_EQ(auth.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(std::string(auth.status().message()), HasSubstr(path));
}

TEST(AuthTest, AuthenticateMetadata) {
  const TokenAuthenticator auth = Loaded();
  const std::string header = absl::StrCat("Bearer ", kBobToken);
  std::multimap<grpc::string_ref, grpc::string_ref> metadata = {{"x-other", "1"}};
  ExpectUnauthenticated(AuthenticateMetadata(auth, metadata), "missing authorization metadata");
  metadata.emplace("authorization", header);
  EXPECT_EQ(*AuthenticateMetadata(auth, metadata), "bob");
  metadata.emplace("authorization", header);
  ExpectUnauthenticated(AuthenticateMetadata(auth, metadata),
                        "authorization: expected one value, got 2");
  EXPECT_EQ(*AuthenticateMetadata(TokenAuthenticator(), metadata), "");
}

TEST(AuthTest, AuthenticateCallReadsTheServerContext) {
  const TokenAuthenticator auth = Loaded();
  grpc::ServerContext context;
  grpc::testing::ServerContextTestSpouse spouse(&context);
  ExpectUnauthenticated(AuthenticateCall(auth, context), "missing authorization metadata");
  spouse.AddClientMetadata("authorization", absl::StrCat("Bearer ", kAliceToken));
  EXPECT_EQ(*AuthenticateCall(auth, context), "alice");
}

TEST(AuthTest, AuthenticateCallUnknownToken) {
  const TokenAuthenticator auth = Loaded();
  grpc::ServerContext context;
  grpc::testing::ServerContextTestSpouse spouse(&context);
  spouse.AddClientMetadata("authorization", "Bearer 0000000000000000000000");
  ExpectUnauthenticated(AuthenticateCall(auth, context), "unknown bearer token");
}

}  // namespace
}  // namespace fd::server

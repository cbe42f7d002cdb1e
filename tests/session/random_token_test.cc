#include "session/random_token.h"

#include <string>

#include "absl/container/flat_hash_set.h"
#include "gtest/gtest.h"

namespace fd::session {
namespace {

TEST(RandomTokenTest, ThirtyTwoLowercaseHexCharacters) {
  for (int i = 0; i < 100; ++i) {
    absl::StatusOr<std::string> token = NewRandomToken();
    ASSERT_TRUE(token.ok()) << token.status();
    ASSERT_EQ(token->size(), 32u);
    for (char c : *token) {
      ASSERT_TRUE((c >= '0' && c <= '9') || (c >= 'a' && c <= 'f')) << *token;
    }
    EXPECT_TRUE(IsWellFormedToken(*token));
  }
}

TEST(RandomTokenTest, UniqueAndUniformOverManyDraws) {
  constexpr int kDraws = 20000;
  absl::flat_hash_set<std::string> seen;
  int hex_counts[16] = {};
  for (int i = 0; i < kDraws; ++i) {
    std::string token = *NewRandomToken();
    for (char c : token) ++hex_counts[c <= '9' ? c - '0' : c - 'a' + 10];
    seen.insert(std::move(token));
  }
  EXPECT_EQ(seen.size(), static_cast<size_t>(kDraws));
  // 640000 hex digits: each value about 40000 times (sd ~ 194); a broken
  // source (all zeros, only low nibbles...) fails this.
  for (int v = 0; v < 16; ++v) EXPECT_NEAR(hex_counts[v], 40000, 1500) << "digit " << v;
}

TEST(RandomTokenTest, WellFormedness) {
  EXPECT_TRUE(IsWellFormedToken("0123456789abcdef0123456789abcdef"));
  EXPECT_FALSE(IsWellFormedToken("0123456789ABCDEF0123456789abcdef"));   // uppercase
  EXPECT_FALSE(IsWellFormedToken("0123456789abcdef0123456789abcde"));    // 31
  EXPECT_FALSE(IsWellFormedToken("0123456789abcdef0123456789abcdef0"));  // 33
  EXPECT_FALSE(IsWellFormedToken("0123456789abcdef0123456789abcdeg"));
  EXPECT_FALSE(IsWellFormedToken(""));
}

TEST(RandomTokenTest, ConstantTimeEquals) {
  EXPECT_TRUE(ConstantTimeEquals("abc", "abc"));
  EXPECT_TRUE(ConstantTimeEquals("", ""));
  EXPECT_FALSE(ConstantTimeEquals("abc", "abd"));
  EXPECT_FALSE(ConstantTimeEquals("abc", "xbc"));
  EXPECT_FALSE(ConstantTimeEquals("abc", "abcd"));
  EXPECT_FALSE(ConstantTimeEquals("abc", ""));
}

}  // namespace
}  // namespace fd::session

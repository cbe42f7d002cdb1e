// base/bounded_text.h: client input quoted in messages stays short.
#include "base/bounded_text.h"

#include <gtest/gtest.h>

#include <string>

namespace fd {
namespace {

TEST(BoundedTextTest, ShortTextIsQuotedWhole) {
  EXPECT_EQ(BoundedText("atlantis"), "atlantis");
  EXPECT_EQ(BoundedText(std::string(kMaxQuotedBytes, 'a')), std::string(kMaxQuotedBytes, 'a'));
}

TEST(BoundedTextTest, LongTextIsCutAndItsLengthSaid) {
  const std::string quoted = BoundedText(std::string(1 << 20, 'x'));
  EXPECT_EQ(quoted, std::string(kMaxQuotedBytes, 'x') + "\u2026 (1048576 bytes)");
}

TEST(BoundedTextTest, NoUtf8CharacterIsSplit) {
  // "é" is two bytes: a cut after 5 bytes of "aéééé" would split one.
  const std::string quoted = BoundedText("a\u00e9\u00e9\u00e9\u00e9", 4);
  EXPECT_EQ(quoted, "a\u00e9\u2026 (9 bytes)");
}

}  // namespace
}  // namespace fd

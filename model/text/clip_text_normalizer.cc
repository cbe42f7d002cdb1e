#include "model/text/clip_text_normalizer.h"

#include <algorithm>
#include <cstring>
#include <string>
#include <utility>

#include "model/text/generated/clip_text_tables.h"

namespace fd::model::clip_text {
namespace {

constexpr char32_t kReplacement = 0xFFFD;

template <typename Range>
bool InRanges(const Range* ranges, size_t size, char32_t c) {
  const Range* end = ranges + size;
  const Range* it =
      std::upper_bound(ranges, end, c, [](char32_t v, const Range& r) { return v < r.first; });
  return it != ranges && c <= (it - 1)->last;
}

bool IsLetter(char32_t c) { return InRanges(kLetterRanges, kLetterRangesSize, c); }
bool IsNumber(char32_t c) { return InRanges(kNumberRanges, kNumberRangesSize, c); }
bool IsCased(char32_t c) { return InRanges(kCasedRanges, kCasedRangesSize, c); }
bool IsCaseIgnorable(char32_t c) {
  return InRanges(kCaseIgnorableRanges, kCaseIgnorableRangesSize, c);
}

uint8_t CombiningClass(char32_t c) {
  const CombiningClassRange* end = kCombiningClasses + kCombiningClassesSize;
  const CombiningClassRange* it =
      std::upper_bound(kCombiningClasses, end, c,
                       [](char32_t v, const CombiningClassRange& r) { return v < r.first; });
  if (it == kCombiningClasses || c > (it - 1)->last) return 0;
  return (it - 1)->ccc;
}

// Entities are looked up by name (ASCII, strcmp order).
const HtmlEntity* FindEntity(const HtmlEntity* table, size_t size, const std::string& name) {
  const HtmlEntity* end = table + size;
  const HtmlEntity* it = std::lower_bound(
      table, end, name,
      [](const HtmlEntity& e, const std::string& n) { return std::strcmp(e.name, n.c_str()) < 0; });
  if (it != end && name == it->name) return it;
  return nullptr;
}

bool IsAsciiAlnum(char32_t c) {
  return (c >= '0' && c <= '9') || (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z');
}
bool IsAsciiDigit(char32_t c) { return c >= '0' && c <= '9'; }
bool IsHexDigit(char32_t c) {
  return IsAsciiDigit(c) || (c >= 'a' && c <= 'f') || (c >= 'A' && c <= 'F');
}

// Windows-1252 for 0x80..0x9F, with the five undefined bytes mapped to
// themselves: ftfy's "sloppy-windows-1252" and Python's _invalid_charrefs.
constexpr char32_t kCp1252High[32] = {
    0x20AC, 0x81,   0x201A, 0x192,  0x201E, 0x2026, 0x2020, 0x2021, 0x2C6,  0x2030, 0x160,
    0x2039, 0x152,  0x8D,   0x17D,  0x8F,   0x90,   0x2018, 0x2019, 0x201C, 0x201D, 0x2022,
    0x2013, 0x2014, 0x2DC,  0x2122, 0x161,  0x203A, 0x153,  0x9D,   0x17E,  0x178};

// ftfy's LIGATURES.
struct Ligature {
  char32_t from;
  const char32_t* to;
};
constexpr Ligature kLigatures[] = {
    {0x132, U"IJ"},       {0x133, U"ij"},      {0x149, U"\u02BCn"}, {0x1C4, U"D\u017D"},
    {0x1C5, U"D\u017E"},  {0x1C6, U"d\u017E"}, {0x1C7, U"LJ"},      {0x1C8, U"Lj"},
    {0x1C9, U"lj"},       {0x1CA, U"NJ"},      {0x1CB, U"Nj"},      {0x1CC, U"nj"},
    {0x1F1, U"DZ"},       {0x1F2, U"Dz"},      {0x1F3, U"dz"},      {0xFB00, U"ff"},
    {0xFB01, U"fi"},      {0xFB02, U"fl"},     {0xFB03, U"ffi"},    {0xFB04, U"ffl"},
    {0xFB05, U"\u017Ft"}, {0xFB06, U"st"},
};

// ---------------------------------------------------------------------------
// ftfy fixes (ftfy/fixes.py, ftfy/chardata.py of 6.3.1).

std::u32string PythonUnescapeOne(std::u32string_view text, size_t amp, size_t* consumed);

// unescape_html: entities matching &#?[0-9A-Za-z]{1,24}; that are in
// html5 (with ';'), ftfy's all-caps set, or numeric references that
// html.unescape decodes completely.
std::u32string FtfyUnescapeHtml(std::u32string_view text) {
  std::u32string out;
  size_t i = 0;
  while (i < text.size()) {
    if (text[i] != '&') {
      out.push_back(text[i++]);
      continue;
    }
    size_t j = i + 1;
    const bool numeric = j < text.size() && text[j] == '#';
    if (numeric) ++j;
    size_t k = 0;
    while (j + k < text.size() && IsAsciiAlnum(text[j + k])) ++k;
    if (k < 1 || k > 24 || j + k >= text.size() || text[j + k] != ';') {
      out.push_back(text[i++]);
      continue;
    }
    const std::u32string_view entity = text.substr(i, j + k + 1 - i);  // "&...;"
    std::string name;
    for (char32_t c : entity.substr(1)) name.push_back(static_cast<char>(c));
    std::u32string replacement(entity);
    if (const HtmlEntity* e = FindEntity(kHtml5Entities, kHtml5EntitiesSize, name)) {
      replacement = DecodeUtf8(e->value);
    } else if (const HtmlEntity* u =
                   FindEntity(kFtfyUppercaseEntities, kFtfyUppercaseEntitiesSize, name)) {
      replacement = DecodeUtf8(u->value);
    } else if (numeric) {
      const std::u32string unescaped = HtmlUnescape(entity);
      if (unescaped.find(U';') == std::u32string::npos) replacement = unescaped;
    }
    out += replacement;
    i += entity.size();
  }
  return out;
}

std::u32string FixC1Controls(std::u32string text) {
  for (char32_t& c : text) {
    if (c >= 0x80 && c <= 0x9F) c = kCp1252High[c - 0x80];
  }
  return text;
}

std::u32string FixLatinLigatures(std::u32string_view text) {
  std::u32string out;
  for (char32_t c : text) {
    const Ligature* lig = std::find_if(std::begin(kLigatures), std::end(kLigatures),
                                       [c](const Ligature& l) { return l.from == c; });
    if (lig != std::end(kLigatures)) {
      out += lig->to;
    } else {
      out.push_back(c);
    }
  }
  return out;
}

std::u32string FixCharacterWidth(std::u32string_view text) {
  std::u32string out;
  for (char32_t c : text) {
    const CodepointString* end = kWidthMap + kWidthMapSize;
    const CodepointString* it = std::lower_bound(
        kWidthMap, end, c, [](const CodepointString& e, char32_t v) { return e.from < v; });
    if (it != end && it->from == c) {
      out += DecodeUtf8(it->to);
    } else {
      out.push_back(c);
    }
  }
  return out;
}

std::u32string UncurlQuotes(std::u32string text) {
  for (char32_t& c : text) {
    if (c == 0x2BC || (c >= 0x2018 && c <= 0x201B))
      c = '\'';
    else if (c >= 0x201C && c <= 0x201F)
      c = '"';
  }
  return text;
}

std::u32string FixLineBreaks(std::u32string_view text) {
  std::u32string out;
  for (size_t i = 0; i < text.size(); ++i) {
    const char32_t c = text[i];
    if (c == '\r') {
      out.push_back('\n');
      if (i + 1 < text.size() && text[i + 1] == '\n') ++i;
    } else if (c == 0x2028 || c == 0x2029 || c == 0x85) {
      out.push_back('\n');
    } else {
      out.push_back(c);
    }
  }
  return out;
}

// "\033\[((?:\d|;)*)([a-zA-Z])"
std::u32string RemoveTerminalEscapes(std::u32string_view text) {
  std::u32string out;
  size_t i = 0;
  while (i < text.size()) {
    if (text[i] == 0x1B && i + 1 < text.size() && text[i + 1] == '[') {
      size_t j = i + 2;
      while (j < text.size() && (IsAsciiDigit(text[j]) || text[j] == ';')) ++j;
      if (j < text.size() &&
          ((text[j] >= 'a' && text[j] <= 'z') || (text[j] >= 'A' && text[j] <= 'Z'))) {
        i = j + 1;
        continue;
      }
    }
    out.push_back(text[i++]);
  }
  return out;
}

bool IsRemovedControl(char32_t c) {
  return c <= 0x08 || c == 0x0B || (c >= 0x0E && c <= 0x1F) || c == 0x7F ||
         (c >= 0x206A && c <= 0x206F) || c == 0xFEFF || (c >= 0xFFF9 && c <= 0xFFFC);
}

std::u32string RemoveControlChars(std::u32string_view text) {
  std::u32string out;
  for (char32_t c : text) {
    if (!IsRemovedControl(c)) out.push_back(c);
  }
  return out;
}

// fix_and_explain for one segment: the fixes in ftfy's order, repeated until
// the text no longer changes.
std::u32string FixSegment(std::u32string text, bool unescape_html) {
  while (true) {
    const std::u32string original = text;
    if (unescape_html) text = FtfyUnescapeHtml(text);
    text = FixC1Controls(std::move(text));
    text = FixLatinLigatures(text);
    text = FixCharacterWidth(text);
    text = UncurlQuotes(std::move(text));
    text = FixLineBreaks(text);
    text = RemoveTerminalEscapes(text);
    text = RemoveControlChars(text);
    text = NormalizeNfc(text);
    if (text == original) return text;
  }
}

// ---------------------------------------------------------------------------
// Python's html.unescape (Lib/html/__init__.py).

bool IsInvalidCodepoint(uint64_t n) {
  return (n >= 0x1 && n <= 0x8) || (n >= 0xE && n <= 0x1F) || (n >= 0x7F && n <= 0x9F) ||
         (n >= 0xFDD0 && n <= 0xFDEF) || n == 0xB || (n & 0xFFFE) == 0xFFFE;
}

std::u32string NumericCharref(uint64_t num) {
  if (num == 0) return std::u32string(1, kReplacement);
  if (num == 0x0D) return U"\r";
  if (num >= 0x80 && num <= 0x9F) return std::u32string(1, kCp1252High[num - 0x80]);
  if ((num >= 0xD800 && num <= 0xDFFF) || num > 0x10FFFF) return std::u32string(1, kReplacement);
  if (IsInvalidCodepoint(num)) return U"";
  return std::u32string(1, static_cast<char32_t>(num));
}

bool IsNameChar(char32_t c) {
  return c != '\t' && c != '\n' && c != '\f' && c != ' ' && c != '<' && c != '&' && c != '#' &&
         c != ';';
}

// The replacement for the charref starting at text[amp] == '&', matching
// &(#[0-9]+;?|#[xX][0-9a-fA-F]+;?|[^\t\n\f <&#;]{1,32};?). *consumed is the
// match length (0: no match at this '&').
std::u32string PythonUnescapeOne(std::u32string_view text, size_t amp, size_t* consumed) {
  *consumed = 0;
  size_t i = amp + 1;
  if (i < text.size() && text[i] == '#') {
    size_t j = i + 1;
    int base = 10;
    if (j < text.size() && IsAsciiDigit(text[j])) {
      base = 10;
    } else if (j + 1 < text.size() && (text[j] == 'x' || text[j] == 'X') &&
               IsHexDigit(text[j + 1])) {
      base = 16;
      ++j;
    } else {
      return U"";
    }
    uint64_t num = 0;
    while (j < text.size() && (base == 16 ? IsHexDigit(text[j]) : IsAsciiDigit(text[j]))) {
      const char32_t c = text[j];
      const uint64_t digit = IsAsciiDigit(c) ? c - '0' : (c | 0x20) - 'a' + 10;
      num = std::min<uint64_t>(num * base + digit, 0x7FFFFFFFull);  // saturate: > 0x10FFFF anyway
      ++j;
    }
    if (j < text.size() && text[j] == ';') ++j;
    *consumed = j - amp;
    return NumericCharref(num);
  }
  size_t j = i;
  while (j < text.size() && j - i < 32 && IsNameChar(text[j])) ++j;
  if (j == i) return U"";
  if (j < text.size() && text[j] == ';') ++j;
  *consumed = j - amp;
  const std::u32string_view s = text.substr(i, j - i);
  auto ascii = [](std::u32string_view v, std::string* out) {
    out->clear();
    for (char32_t c : v) {
      if (c > 0x7F) return false;
      out->push_back(static_cast<char>(c));
    }
    return true;
  };
  std::string name;
  if (ascii(s, &name)) {
    if (const HtmlEntity* e = FindEntity(kHtml5Entities, kHtml5EntitiesSize, name)) {
      return DecodeUtf8(e->value);
    }
  }
  // "find the longest matching name (as defined by the standard)"
  for (size_t x = s.size() - 1; x >= 2 && x < s.size(); --x) {
    if (ascii(s.substr(0, x), &name)) {
      if (const HtmlEntity* e = FindEntity(kHtml5Entities, kHtml5EntitiesSize, name)) {
        return DecodeUtf8(e->value) + std::u32string(s.substr(x));
      }
    }
  }
  return U"&" + std::u32string(s);
}

// ---------------------------------------------------------------------------
// NFC (Unicode Standard Annex #15), with algorithmic Hangul.

constexpr char32_t kSBase = 0xAC00, kLBase = 0x1100, kVBase = 0x1161, kTBase = 0x11A7;
constexpr int kLCount = 19, kVCount = 21, kTCount = 28, kNCount = kVCount * kTCount,
              kSCount = kLCount * kNCount;

void Decompose(char32_t c, std::u32string* out) {
  if (c >= kSBase && c < kSBase + kSCount) {
    const int s = static_cast<int>(c - kSBase);
    out->push_back(kLBase + s / kNCount);
    out->push_back(kVBase + (s % kNCount) / kTCount);
    if (s % kTCount != 0) out->push_back(kTBase + s % kTCount);
    return;
  }
  const Decomposition* end = kDecompositions + kDecompositionsSize;
  const Decomposition* it = std::lower_bound(
      kDecompositions, end, c, [](const Decomposition& d, char32_t v) { return d.code < v; });
  if (it == end || it->code != c) {
    out->push_back(c);
    return;
  }
  Decompose(it->first, out);
  if (it->second != 0) Decompose(it->second, out);
}

char32_t Compose(char32_t a, char32_t b) {
  if (a >= kLBase && a < kLBase + kLCount && b >= kVBase && b < kVBase + kVCount) {
    return kSBase + ((a - kLBase) * kVCount + (b - kVBase)) * kTCount;
  }
  if (a >= kSBase && a < kSBase + kSCount && (a - kSBase) % kTCount == 0 && b > kTBase &&
      b < kTBase + kTCount) {
    return a + (b - kTBase);
  }
  const Composition* end = kCompositions + kCompositionsSize;
  const Composition* it =
      std::lower_bound(kCompositions, end, std::make_pair(a, b),
                       [](const Composition& c, std::pair<char32_t, char32_t> v) {
                         return std::make_pair(c.first, c.second) < v;
                       });
  if (it != end && it->first == a && it->second == b) return it->composite;
  return 0;
}

}  // namespace

// ---------------------------------------------------------------------------

std::u32string DecodeUtf8(std::string_view text) {
  std::u32string out;
  out.reserve(text.size());
  size_t i = 0;
  while (i < text.size()) {
    const unsigned char b0 = static_cast<unsigned char>(text[i]);
    int len = 0;
    char32_t c = 0;
    char32_t min = 0;
    if (b0 < 0x80) {
      out.push_back(b0);
      ++i;
      continue;
    } else if ((b0 & 0xE0) == 0xC0) {
      len = 2, c = b0 & 0x1F, min = 0x80;
    } else if ((b0 & 0xF0) == 0xE0) {
      len = 3, c = b0 & 0x0F, min = 0x800;
    } else if ((b0 & 0xF8) == 0xF0) {
      len = 4, c = b0 & 0x07, min = 0x10000;
    }
    bool ok = len > 0 && i + len <= text.size();
    for (int k = 1; ok && k < len; ++k) {
      const unsigned char b = static_cast<unsigned char>(text[i + k]);
      ok = (b & 0xC0) == 0x80;
      c = (c << 6) | (b & 0x3F);
    }
    ok = ok && c >= min && c <= 0x10FFFF && !(c >= 0xD800 && c <= 0xDFFF);
    if (!ok) {
      out.push_back(kReplacement);
      ++i;
      continue;
    }
    out.push_back(c);
    i += len;
  }
  return out;
}

std::string EncodeUtf8(std::u32string_view text) {
  std::string out;
  out.reserve(text.size());
  for (char32_t c : text) {
    if (c < 0x80) {
      out.push_back(static_cast<char>(c));
    } else if (c < 0x800) {
      out.push_back(static_cast<char>(0xC0 | (c >> 6)));
      out.push_back(static_cast<char>(0x80 | (c & 0x3F)));
    } else if (c < 0x10000) {
      out.push_back(static_cast<char>(0xE0 | (c >> 12)));
      out.push_back(static_cast<char>(0x80 | ((c >> 6) & 0x3F)));
      out.push_back(static_cast<char>(0x80 | (c & 0x3F)));
    } else {
      out.push_back(static_cast<char>(0xF0 | (c >> 18)));
      out.push_back(static_cast<char>(0x80 | ((c >> 12) & 0x3F)));
      out.push_back(static_cast<char>(0x80 | ((c >> 6) & 0x3F)));
      out.push_back(static_cast<char>(0x80 | (c & 0x3F)));
    }
  }
  return out;
}

bool IsPythonSpace(char32_t c) {
  return (c >= 0x09 && c <= 0x0D) || (c >= 0x1C && c <= 0x20) || c == 0x85 || c == 0xA0 ||
         c == 0x1680 || (c >= 0x2000 && c <= 0x200A) || c == 0x2028 || c == 0x2029 || c == 0x202F ||
         c == 0x205F || c == 0x3000;
}

std::u32string FtfyFixText(std::u32string_view text) {
  std::u32string out;
  bool unescape_html = true;  // "auto": off from the first line containing '<'
  size_t pos = 0;
  while (pos < text.size()) {
    const size_t newline = text.find(U'\n', pos);
    const size_t end = newline == std::u32string_view::npos ? text.size() : newline + 1;
    std::u32string segment(text.substr(pos, end - pos));
    if (unescape_html && segment.find(U'<') != std::u32string::npos) unescape_html = false;
    out += FixSegment(std::move(segment), unescape_html);
    pos = end;
  }
  return out;
}

std::u32string HtmlUnescape(std::u32string_view text) {
  if (text.find(U'&') == std::u32string_view::npos) return std::u32string(text);
  std::u32string out;
  size_t i = 0;
  while (i < text.size()) {
    if (text[i] == '&') {
      size_t consumed = 0;
      std::u32string replacement = PythonUnescapeOne(text, i, &consumed);
      if (consumed > 0) {
        out += replacement;
        i += consumed;
        continue;
      }
    }
    out.push_back(text[i++]);
  }
  return out;
}

std::u32string PythonLower(std::u32string_view text) {
  std::u32string out;
  out.reserve(text.size());
  for (size_t i = 0; i < text.size(); ++i) {
    const char32_t c = text[i];
    if (c == 0x130) {  // LATIN CAPITAL LETTER I WITH DOT ABOVE -> i + COMBINING DOT ABOVE
      out += U"i\u0307";
      continue;
    }
    if (c == 0x3A3) {
      // Final_Sigma: \p{cased}\p{case-ignorable}* SIGMA !(\p{case-ignorable}*\p{cased})
      size_t j = i;
      while (j > 0 && IsCaseIgnorable(text[j - 1])) --j;
      bool final_sigma = j > 0 && IsCased(text[j - 1]);
      if (final_sigma) {
        size_t k = i + 1;
        while (k < text.size() && IsCaseIgnorable(text[k])) ++k;
        final_sigma = k == text.size() || !IsCased(text[k]);
      }
      out.push_back(final_sigma ? 0x3C2 : 0x3C3);
      continue;
    }
    const CodepointPair* end = kLowercase + kLowercaseSize;
    const CodepointPair* it = std::lower_bound(
        kLowercase, end, c, [](const CodepointPair& p, char32_t v) { return p.from < v; });
    out.push_back(it != end && it->from == c ? it->to : c);
  }
  return out;
}

std::u32string NormalizeNfc(std::u32string_view text) {
  // Fast path: ASCII is always NFC.
  if (std::all_of(text.begin(), text.end(), [](char32_t c) { return c < 0x80; })) {
    return std::u32string(text);
  }
  std::u32string d;
  for (char32_t c : text) Decompose(c, &d);
  // Canonical ordering: stable sort of each run of non-starters by class.
  for (size_t i = 0; i < d.size();) {
    if (CombiningClass(d[i]) == 0) {
      ++i;
      continue;
    }
    size_t j = i;
    while (j < d.size() && CombiningClass(d[j]) != 0) ++j;
    std::stable_sort(d.begin() + i, d.begin() + j,
                     [](char32_t a, char32_t b) { return CombiningClass(a) < CombiningClass(b); });
    i = j;
  }
  // Canonical composition.
  if (d.empty()) return d;
  std::u32string out;
  out.push_back(d[0]);
  size_t starter_pos = 0;
  bool have_starter = CombiningClass(d[0]) == 0;
  int last_class = have_starter ? 0 : 256;
  for (size_t i = 1; i < d.size(); ++i) {
    const char32_t c = d[i];
    const int c_class = CombiningClass(c);
    if (have_starter && (last_class < c_class || last_class == 0)) {
      if (const char32_t composite = Compose(out[starter_pos], c); composite != 0) {
        out[starter_pos] = composite;
        continue;
      }
    }
    if (c_class == 0) {
      starter_pos = out.size();
      have_starter = true;
    }
    last_class = c_class;
    out.push_back(c);
  }
  return out;
}

std::string CleanText(std::string_view utf8_text) {
  // basic_clean
  std::u32string text = FtfyFixText(DecodeUtf8(utf8_text));
  text = HtmlUnescape(HtmlUnescape(text));
  // whitespace_clean (the strip of basic_clean is subsumed): runs of
  // whitespace -> one space, then strip.
  std::u32string collapsed;
  for (char32_t c : text) {
    if (IsPythonSpace(c)) {
      if (collapsed.empty() || collapsed.back() != ' ') collapsed.push_back(' ');
    } else {
      collapsed.push_back(c);
    }
  }
  size_t begin = 0;
  size_t end = collapsed.size();
  while (begin < end && collapsed[begin] == ' ') ++begin;
  while (end > begin && collapsed[end - 1] == ' ') --end;
  return EncodeUtf8(PythonLower(std::u32string_view(collapsed).substr(begin, end - begin)));
}

std::vector<std::string> PreTokenize(std::string_view cleaned_text) {
  static const std::u32string kSpecial[] = {U"<|startoftext|>", U"<|endoftext|>"};
  // Contractions in the pattern's order ('s|'t|'re|'ve|'m|'ll|'d), matched
  // case-insensitively (the pattern has re.IGNORECASE).
  static const std::u32string kContractions[] = {U"s", U"t", U"re", U"ve", U"m", U"ll", U"d"};
  const std::u32string text = DecodeUtf8(cleaned_text);
  auto fold = [](char32_t c) -> char32_t {
    if (c >= 'A' && c <= 'Z') return c + 32;
    if (c == 0x17F) return 's';  // LATIN SMALL LETTER LONG S folds to s
    return c;
  };
  std::vector<std::string> words;
  size_t i = 0;
  while (i < text.size()) {
    bool matched = false;
    for (const std::u32string& special : kSpecial) {
      if (text.compare(i, special.size(), special) == 0) {
        words.push_back(EncodeUtf8(special));
        i += special.size();
        matched = true;
        break;
      }
    }
    if (matched) continue;
    if (text[i] == '\'') {
      for (const std::u32string& suffix : kContractions) {
        if (i + 1 + suffix.size() > text.size()) continue;
        bool equal = true;
        for (size_t k = 0; k < suffix.size() && equal; ++k)
          equal = fold(text[i + 1 + k]) == suffix[k];
        if (equal) {
          words.push_back(EncodeUtf8(std::u32string_view(text).substr(i, 1 + suffix.size())));
          i += 1 + suffix.size();
          matched = true;
          break;
        }
      }
      if (matched) continue;
    }
    const char32_t c = text[i];
    size_t j = i + 1;
    if (IsLetter(c)) {
      while (j < text.size() && IsLetter(text[j])) ++j;
    } else if (IsNumber(c)) {
      // [\p{N}]: one character per word
    } else if (!IsPythonSpace(c)) {
      while (j < text.size() && !IsPythonSpace(text[j]) && !IsLetter(text[j]) &&
             !IsNumber(text[j])) {
        ++j;
      }
    } else {
      i = j;  // whitespace separates words
      continue;
    }
    words.push_back(EncodeUtf8(std::u32string_view(text).substr(i, j - i)));
    i = j;
  }
  return words;
}

}  // namespace fd::model::clip_text

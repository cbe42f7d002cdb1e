// Unicode and HTML data for the CLIP tokenizer's text clean-up
// (model/text/clip_text_normalizer.h), generated from Python's unicodedata and
// html.entities by scripts/gen_clip_text_tables.py into clip_text_tables.cc.
// Internal to fd::model. All arrays are sorted by their first field.
#ifndef FD_MODEL_TEXT_GENERATED_CLIP_TEXT_TABLES_H_
#define FD_MODEL_TEXT_GENERATED_CLIP_TEXT_TABLES_H_

#include <cstddef>
#include <cstdint>

namespace fd::model::clip_text {

struct CodepointRange {
  char32_t first;
  char32_t last;  // inclusive
};
struct CodepointPair {
  char32_t from;
  char32_t to;
};
struct CodepointString {
  char32_t from;
  const char* to;  // UTF-8
};
struct CombiningClassRange {
  char32_t first;
  char32_t last;  // inclusive
  uint8_t ccc;
};
struct Decomposition {  // canonical, one level
  char32_t code;
  char32_t first;
  char32_t second;  // 0 for a singleton
};
struct Composition {  // primary composite of (first, second)
  char32_t first;
  char32_t second;
  char32_t composite;
};
struct HtmlEntity {
  const char* name;   // as in html.entities.html5, e.g. "amp;" or "amp"
  const char* value;  // UTF-8
};

extern const CodepointRange kLetterRanges[];  // \p{L}
extern const size_t kLetterRangesSize;
extern const CodepointRange kNumberRanges[];  // \p{N}
extern const size_t kNumberRangesSize;
extern const CodepointRange kCaseIgnorableRanges[];
extern const size_t kCaseIgnorableRangesSize;
extern const CodepointRange kCasedRanges[];
extern const size_t kCasedRangesSize;
extern const CodepointPair kLowercase[];  // str.lower(), one-to-one part
extern const size_t kLowercaseSize;
extern const CombiningClassRange kCombiningClasses[];
extern const size_t kCombiningClassesSize;
extern const Decomposition kDecompositions[];
extern const size_t kDecompositionsSize;
extern const Composition kCompositions[];  // sorted by (first, second)
extern const size_t kCompositionsSize;
extern const CodepointString kWidthMap[];  // ftfy's WIDTH_MAP
extern const size_t kWidthMapSize;
extern const HtmlEntity kHtml5Entities[];  // sorted by name (strcmp order)
extern const size_t kHtml5EntitiesSize;
// ftfy's all-caps entities ("EACUTE;" -> "É"), sorted by name.
extern const HtmlEntity kFtfyUppercaseEntities[];
extern const size_t kFtfyUppercaseEntitiesSize;

}  // namespace fd::model::clip_text

#endif  // FD_MODEL_TEXT_GENERATED_CLIP_TEXT_TABLES_H_

// The text clean-up and pre-tokenization of OpenAI CLIP's
// simple_tokenizer.py (github openai/CLIP @ d05afc43), which SD1.5's
// CLIPTokenizer reproduces:
//   basic_clean:      ftfy.fix_text(text); html.unescape(html.unescape(text)); strip()
//   whitespace_clean: re.sub(r"\s+", " ", text).strip()
//   then str.lower(), then regex.findall of
//   <\|startoftext\|>|<\|endoftext\|>|'s|'t|'re|'ve|'m|'ll|'d|[\p{L}]+|[\p{N}]|[^\s\p{L}\p{N}]+
//
// ftfy 6.3.1's fix_text is ported except its mojibake repair (fix_encoding:
// re-decoding text that was decoded with the wrong codec, detected by ftfy's
// "badness" heuristic); the other fixes are applied in ftfy's order until the
// text stops changing, per line: unescape_html (not for lines from the first
// one containing '<' on), fix_c1_controls, fix_latin_ligatures,
// fix_character_width, uncurl_quotes, fix_line_breaks,
// remove_terminal_escapes, remove_control_chars, NFC.
// Unicode properties come from Python 3.11's unicodedata (Unicode 14.0; the
// reference's `regex` module uses 15.0 for \p{L}/\p{N}, which only differs
// for characters added in 15.0). Invalid UTF-8 input bytes become U+FFFD.
//
// All functions are pure and thread-safe.
#ifndef FD_MODEL_TEXT_CLIP_TEXT_NORMALIZER_H_
#define FD_MODEL_TEXT_CLIP_TEXT_NORMALIZER_H_

#include <string>
#include <string_view>
#include <vector>

namespace fd::model::clip_text {

std::u32string DecodeUtf8(std::string_view text);
std::string EncodeUtf8(std::u32string_view text);

// ftfy.fix_text with the default configuration, minus fix_encoding.
std::u32string FtfyFixText(std::u32string_view text);
// Python's html.unescape.
std::u32string HtmlUnescape(std::u32string_view text);
// Python's str.lower() (full case mapping, Final_Sigma rule).
std::u32string PythonLower(std::u32string_view text);
// Unicode NFC.
std::u32string NormalizeNfc(std::u32string_view text);

// whitespace_clean(basic_clean(text)).lower(), as UTF-8.
std::string CleanText(std::string_view utf8_text);

// regex.findall of the CLIP pattern over cleaned text (UTF-8 in and out).
std::vector<std::string> PreTokenize(std::string_view cleaned_text);

// Python's str.isspace() for one code point.
bool IsPythonSpace(char32_t c);

}  // namespace fd::model::clip_text

#endif  // FD_MODEL_TEXT_CLIP_TEXT_NORMALIZER_H_

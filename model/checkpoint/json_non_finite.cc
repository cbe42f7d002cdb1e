// See json_non_finite.h.
#include "model/checkpoint/json_non_finite.h"

#include <cstring>
#include <limits>
#include <string>

#include "absl/strings/str_cat.h"

namespace fd::model {
namespace {

// Python's json module writes nan/inf as the bare tokens NaN, Infinity and
// -Infinity, which are not JSON. Outside string literals (where letters only
// occur in true/false/null and these tokens) they are replaced by these
// marker strings, which the number readers below turn back into doubles.
constexpr char kNonFiniteMarker[] =
    "\x01"
    "fd-nonfinite:";

}  // namespace

std::string QuoteNonFiniteJsonTokens(std::string_view text) {
  static constexpr const char* kTokens[] = {"-Infinity", "Infinity", "NaN"};
  std::string out;
  out.reserve(text.size());
  bool in_string = false;
  for (size_t i = 0; i < text.size(); ++i) {
    const char c = text[i];
    if (in_string) {
      out.push_back(c);
      if (c == '\\' && i + 1 < text.size()) {
        out.push_back(text[++i]);
      } else if (c == '"') {
        in_string = false;
      }
      continue;
    }
    if (c == '"') {
      in_string = true;
      out.push_back(c);
      continue;
    }
    bool replaced = false;
    for (const char* token : kTokens) {
      const size_t length = std::strlen(token);
      if (text.substr(i, length) == token) {
        // The marker's control character must be escaped inside JSON text.
        absl::StrAppend(&out, "\"\\u0001", kNonFiniteMarker + 1, token, "\"");
        i += length - 1;
        replaced = true;
        break;
      }
    }
    if (!replaced) out.push_back(c);
  }
  return out;
}

std::optional<double> NonFiniteFromMarker(const nlohmann::json& value) {
  if (!value.is_string()) return std::nullopt;
  const std::string& text = value.get_ref<const std::string&>();
  const std::string marker = kNonFiniteMarker;
  if (text.compare(0, marker.size(), marker) != 0) return std::nullopt;
  const std::string token = text.substr(marker.size());
  if (token == "NaN") return std::numeric_limits<double>::quiet_NaN();
  if (token == "Infinity") return std::numeric_limits<double>::infinity();
  return -std::numeric_limits<double>::infinity();
}

}  // namespace fd::model

// Client input quoted in a status message or a log field, bounded: an error
// must name what was wrong without echoing unbounded input (a 1 MiB
// environment name must not become a 1 MiB status message, which a client
// with gRPC's 8 KiB metadata limit cannot even receive, nor a 1 MiB log
// line). Thread-safety: pure functions.
#ifndef FD_BASE_BOUNDED_TEXT_H_
#define FD_BASE_BOUNDED_TEXT_H_

#include <cstddef>
#include <string>
#include <string_view>

namespace fd {

// The longest client-supplied text quoted whole.
inline constexpr size_t kMaxQuotedBytes = 128;

// `text` itself when it is at most `max_bytes` long; otherwise its first
// bytes (cut before a UTF-8 continuation byte, so no character is split)
// followed by "… (N bytes)" with N the full length.
inline std::string BoundedText(std::string_view text, size_t max_bytes = kMaxQuotedBytes) {
  if (text.size() <= max_bytes) return std::string(text);
  size_t cut = max_bytes;
  while (cut > 0 && (static_cast<unsigned char>(text[cut]) & 0xC0) == 0x80) --cut;
  return std::string(text.substr(0, cut)) + "\u2026 (" + std::to_string(text.size()) + " bytes)";
}

}  // namespace fd

#endif  // FD_BASE_BOUNDED_TEXT_H_

// Debian's abseil (20220623) is built with its own absl::string_view rather
// than an alias of std::string_view (ABSL_OPTION_USE_STD_STRING_VIEW 0), so
// absl::StrCat, absl::Cord and the string-keyed hash maps do not accept a
// std::string_view. Our APIs use std::string_view (as model/ does) and
// convert at those calls; with an abseil that aliases the two this is a
// no-op.
#ifndef FD_SESSION_STRING_VIEW_COMPAT_H_
#define FD_SESSION_STRING_VIEW_COMPAT_H_

#include <string_view>

#include "absl/strings/string_view.h"

namespace fd::session {

inline absl::string_view ToAbsl(std::string_view text) {
  return absl::string_view(text.data(), text.size());
}

}  // namespace fd::session

#endif  // FD_SESSION_STRING_VIEW_COMPAT_H_

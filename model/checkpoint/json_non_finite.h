// Non-finite numbers in JSON written by Python (internal to fd::model).
//
// diffusers writes configs with Python's json module, which emits nan/inf as
// the bare tokens NaN, Infinity and -Infinity (e.g. a scheduler's
// lambda_min_clipped = -Infinity). They are not JSON, so nlohmann rejects
// them. QuoteNonFiniteJsonTokens rewrites them, outside string literals, into
// marker strings that cannot collide with real string values, and
// NonFiniteFromMarker turns such a marker back into the double.
// Thread-safe (pure functions); never throw.
#ifndef FD_MODEL_CHECKPOINT_JSON_NON_FINITE_H_
#define FD_MODEL_CHECKPOINT_JSON_NON_FINITE_H_

#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <string_view>

namespace fd::model {

// `text` with every bare NaN / Infinity / -Infinity token outside string
// literals replaced by a marker string.
std::string QuoteNonFiniteJsonTokens(std::string_view text);

// The double a marker string stands for; nullopt for any other value
// (including an ordinary string "NaN").
std::optional<double> NonFiniteFromMarker(const nlohmann::json& value);

}  // namespace fd::model

#endif  // FD_MODEL_CHECKPOINT_JSON_NON_FINITE_H_

// Export and import of a SessionState as a compact, versioned binary blob,
// for resuming a session elsewhere (e.g. moving it between servers).
//
// The blob holds the state only: no session id, resume secret or client
// identity (those belong to the store that issues them), so a blob may be
// handed to the client that owns the session. Pixel data is zstd-compressed;
// the layout is in state_blob_format.h.
#ifndef FD_SESSION_STATE_BLOB_H_
#define FD_SESSION_STATE_BLOB_H_

#include <string>
#include <string_view>

#include "absl/status/statusor.h"
#include "session/session_state.h"

namespace fd::session {

// Serialises `state` (format version kStateBlobVersion). INTERNAL only if
// zstd fails. Thread-safety: reads `state`; the caller serialises access to
// it (Session::ExportState does).
absl::StatusOr<std::string> ExportState(const SessionState& state);

// Parses and validates a blob written by ExportState. INVALID_ARGUMENT naming
// the field for a bad magic, an unsupported version, truncation, trailing
// bytes, a checksum mismatch, a size that does not match the settings, bad
// zstd data or an invalid field value (the SessionState::Restore checks).
// Never allocates more than the blob's settings allow (kMaxImageSide bounds
// them). Thread-safety: pure function.
absl::StatusOr<SessionState> ImportState(std::string_view blob);

}  // namespace fd::session

#endif  // FD_SESSION_STATE_BLOB_H_

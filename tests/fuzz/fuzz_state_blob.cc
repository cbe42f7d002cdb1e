// Fuzz target: a session state blob (what a client may hand back to move its
// session between servers) -> session::ImportState.
//
// Input: the blob.
// Properties: an imported state satisfies SessionState's invariants (checked
// by Restore) and round-trips: exported again and re-imported it has the
// same settings, counters and images; a bad blob is INVALID_ARGUMENT with a
// bounded message.
#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>

#include "session/state_blob.h"
#include "tests/fuzz/fuzz_check.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string_view blob(reinterpret_cast<const char*>(data), size);
  absl::StatusOr<fd::session::SessionState> state = fd::session::ImportState(blob);
  if (!state.ok()) {
    fd::fuzz::CheckError(state.status(), absl::StatusCode::kInvalidArgument, "");
    return 0;
  }
  absl::StatusOr<std::string> again = fd::session::ExportState(*state);
  FD_FUZZ_CHECK(again.ok(), "an imported state exports");
  absl::StatusOr<fd::session::SessionState> round = fd::session::ImportState(*again);
  FD_FUZZ_CHECK(round.ok(), "an exported state imports");
  FD_FUZZ_CHECK(*round == *state, "a state round-trips through its blob");
  return 0;
}

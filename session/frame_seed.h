// Per-frame noise seeds.
//
// A session keeps no live random generator. The noise (and VAE sample) of
// frame k is drawn from a fresh generator seeded with FrameSeed(seed, k),
// where k counts the frames the session has rendered (SessionState::
// frame_counter()). So a session is reproducible from (seed, k) alone, does
// not depend on which other sessions share its batches, survives export /
// import with 8 bytes of state, and a rejected frame retried with the same k
// gets the same noise.
#ifndef FD_SESSION_FRAME_SEED_H_
#define FD_SESSION_FRAME_SEED_H_

#include <cstdint>

namespace fd::session {

// SplitMix64's output function (Steele, Lea, Flood 2014; the variant in
// java.util.SplittableRandom): a bijection on 64-bit values with full
// avalanche.
constexpr uint64_t Mix64(uint64_t z) {
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
  return z ^ (z >> 31);
}

// The golden-ratio increment of SplitMix64.
inline constexpr uint64_t kSplitMix64Gamma = 0x9e3779b97f4a7c15ULL;
// Separates frame seeds from any other use of the same session seed.
inline constexpr uint64_t kFrameSeedDomain = 0x6644'5f66'7261'6d65ULL;  // "fD_frame"

// The seed of frame `frame_counter` of a session seeded with `session_seed`:
// output number frame_counter (0-based) of a SplitMix64 generator whose state
// starts at Mix64(session_seed ^ kFrameSeedDomain). Distinct frame counters of
// one session give distinct seeds (SplitMix64 has period 2^64). These values
// are part of the reproducibility contract: changing this function changes
// every session's frames. Thread-safety: pure function.
constexpr uint64_t FrameSeed(uint64_t session_seed, uint64_t frame_counter) {
  const uint64_t state = Mix64(session_seed ^ kFrameSeedDomain);
  return Mix64(state + kSplitMix64Gamma * (frame_counter + 1));
}

}  // namespace fd::session

#endif  // FD_SESSION_FRAME_SEED_H_

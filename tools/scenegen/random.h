// Deterministic hashing and per-pixel random numbers.
//
// Every pixel owns a PixelRng seeded from (seed, frame, pixel index), so the
// rendered image does not depend on how rows are split across threads or in
// which order they run: there is no shared RNG state anywhere.
#ifndef FD_TOOLS_SCENEGEN_RANDOM_H_
#define FD_TOOLS_SCENEGEN_RANDOM_H_

#include <cstdint>

namespace fd::scenegen {

// SplitMix64 finaliser: a bijective, well-mixing 64-bit hash.
constexpr uint64_t Mix64(uint64_t z) {
  z += 0x9E3779B97F4A7C15ull;
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
  return z ^ (z >> 31);
}

// Hash of up to four integers; order matters.
constexpr uint64_t HashInts(uint64_t a, uint64_t b = 0, uint64_t c = 0, uint64_t d = 0) {
  return Mix64(Mix64(Mix64(Mix64(a) ^ b) ^ c) ^ d);
}

// Uniform float in [0, 1) from the top 24 bits of a hash.
constexpr float HashToUnitFloat(uint64_t h) {
  return static_cast<float>(h >> 40) * (1.0f / 16777216.0f);
}

// Small sequential generator (SplitMix64 stream). Not thread-safe: one per
// pixel (or per scene build), never shared between threads.
class PixelRng {
 public:
  explicit constexpr PixelRng(uint64_t state) : state_(state) {}
  PixelRng(uint64_t seed, uint64_t frame, uint64_t pixel)
      : state_(HashInts(seed, frame, pixel, 0x5CE4E6E4ull)) {}

  uint64_t NextU64() {
    state_ += 0x9E3779B97F4A7C15ull;
    uint64_t z = state_;
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
  }
  // Uniform in [0, 1).
  float NextFloat() { return HashToUnitFloat(NextU64()); }
  // Uniform in [lo, hi).
  float Uniform(float lo, float hi) { return lo + (hi - lo) * NextFloat(); }

 private:
  uint64_t state_;
};

}  // namespace fd::scenegen

#endif  // FD_TOOLS_SCENEGEN_RANDOM_H_

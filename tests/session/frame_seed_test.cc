#include "session/frame_seed.h"

#include <bitset>
#include <cstdint>

#include "absl/container/flat_hash_set.h"
#include "gtest/gtest.h"

namespace fd::session {
namespace {

TEST(FrameSeedTest, Mix64IsSplitMix64) {
  // The first output of the SplitMix64 reference generator seeded with 0.
  EXPECT_EQ(Mix64(kSplitMix64Gamma), 0xe220a8397b1dcdafULL);
}

TEST(FrameSeedTest, StableValues) {
  // Computed independently (Python) from the formula documented in
  // frame_seed.h. A change here changes every session's frames.
  EXPECT_EQ(FrameSeed(0, 0), 0x85aaae284ca94690ULL);
  EXPECT_EQ(FrameSeed(0, 1), 0xd82c22e5df4d96baULL);
  EXPECT_EQ(FrameSeed(42, 0), 0xc19e63734332d9caULL);
  EXPECT_EQ(FrameSeed(42, 1), 0x59f2d376254922b3ULL);
  EXPECT_EQ(FrameSeed(42, 499), 0xc1018d9b8ab60d3eULL);
  EXPECT_EQ(FrameSeed(123456789, 7), 0xb26a8b1d77163ee4ULL);
  EXPECT_EQ(FrameSeed(UINT64_MAX, UINT64_MAX), 0x072ffb3917196f7eULL);
  static_assert(FrameSeed(42, 0) == 0xc19e63734332d9caULL, "usable at compile time");
}

TEST(FrameSeedTest, DistinctOverSessionsAndFrames) {
  // Neighbouring session seeds and frame counters (the common case: seeds
  // 1, 2, 3... and frames 0, 1, 2...) must not collide.
  absl::flat_hash_set<uint64_t> seen;
  for (uint64_t session_seed = 0; session_seed < 256; ++session_seed) {
    for (uint64_t frame = 0; frame < 256; ++frame) {
      seen.insert(FrameSeed(session_seed, frame));
    }
  }
  EXPECT_EQ(seen.size(), 256u * 256u);
  // Seed s frame k is not seed s+1 frame k-1 (a plain sum would collide).
  EXPECT_NE(FrameSeed(1, 1), FrameSeed(2, 0));
}

// Flipping one input bit flips about half of the output bits.
TEST(FrameSeedTest, WellMixed) {
  double total_flips = 0;
  int samples = 0;
  int min_flips = 64;
  for (uint64_t base = 0; base < 64; ++base) {
    const uint64_t session_seed = 1000 + base * 7919;
    const uint64_t frame = base * 31;
    const uint64_t reference = FrameSeed(session_seed, frame);
    for (int bit = 0; bit < 64; ++bit) {
      for (uint64_t other : {FrameSeed(session_seed ^ (1ULL << bit), frame),
                             FrameSeed(session_seed, frame ^ (1ULL << bit))}) {
        const int flips = static_cast<int>(std::bitset<64>(reference ^ other).count());
        total_flips += flips;
        min_flips = std::min(min_flips, flips);
        ++samples;
      }
    }
  }
  const double mean = total_flips / samples;
  EXPECT_NEAR(mean, 32.0, 0.5) << "over " << samples << " single-bit changes";
  EXPECT_GE(min_flips, 10);
  // Each output bit is set about half the time over consecutive frames.
  int ones[64] = {};
  const int frames = 4096;
  for (int k = 0; k < frames; ++k) {
    const uint64_t seed = FrameSeed(7, k);
    for (int bit = 0; bit < 64; ++bit) ones[bit] += (seed >> bit) & 1;
  }
  for (int bit = 0; bit < 64; ++bit) {
    EXPECT_NEAR(ones[bit], frames / 2, 200) << "bit " << bit;
  }
}

}  // namespace
}  // namespace fd::session
